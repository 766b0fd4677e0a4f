"""``ti-cmax params [SECTION]``: every config key with its value, unit, allowed values and meaning.

Generated from the config dataclasses (:func:`ti_cmax.config.param` declarations), so it cannot drift from what
``--config`` / ``--set`` accept. ``--config`` and ``--set`` are applied (and checked), so this also validates a
config file. ``--markdown`` prints the table (as in the README).
"""
from __future__ import annotations

import argparse
import importlib

HELP = "list the config keys (default, unit, allowed values, meaning); SECTION: e.g. frontend, backend, simulate"

# command whose --config/--set keys a SECTION may name -> (module, class)
CONFIGS = {
    "slam": ("ti_cmax.config", "SlamConfig"),
    "simulate": ("ti_cmax.simulate.config", "SimulatorConfig"),
    "evaluate": ("ti_cmax.metrics", "EvaluationConfig"),
    "grayscale": ("ti_cmax.commands.grayscale", "GrayscaleCommandConfig"),
    "baseline": ("ti_cmax.pipelines.baselines", "BaselineConfig"),
    "benchmark": ("ti_cmax.pipelines.evaluation.benchmark", "BenchmarkConfig"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("section", nargs="?", default=None, metavar="SECTION",
                        help="a section (dataset, frontend, backend, output, rtpt, gae, smt, ...) or a command "
                             "(slam, simulate, evaluate, grayscale, baseline, benchmark); default: slam")
    parser.add_argument("--markdown", action="store_true", help="print a markdown table")


def config_class(command: str):
    module, name = CONFIGS[command]
    return getattr(importlib.import_module(module), name)


def resolve(section: str | None):
    """(config class, section prefix or '') for SECTION; InputError naming the choices when unknown."""
    from dataclasses import fields, is_dataclass

    from ..config import _hints
    from ..errors import InputError

    section = section or "slam"
    if section in CONFIGS:
        return config_class(section), ""
    names = list(CONFIGS)
    for command in CONFIGS:
        cls = config_class(command)
        hints = _hints(cls)
        for f in fields(cls):
            if is_dataclass(hints[f.name]):
                names.append(f.name)
                if f.name == section:
                    return cls, f.name
    raise InputError(f"unknown section {section!r} (expected one of {', '.join(dict.fromkeys(names))})")


def rows(cfg, prefix: str = ""):
    """(key, value, unit, rule, help) of every leaf key of the config instance ``cfg`` under ``prefix``."""
    from ..config import iter_params, rule_text

    out = []
    for key, f, _ in iter_params(type(cfg)):
        if prefix and not key.startswith(prefix + "."):
            continue
        value = cfg
        for part in key.split("."):
            value = getattr(value, part)
        out.append((key, value, f.metadata.get("unit", ""), rule_text(f.metadata), f.metadata.get("help", "")))
    return out


def _fmt(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return repr(value) if value == "" else value
    if isinstance(value, tuple):
        return "[" + ", ".join(str(v) for v in value) + "]"
    return f"{value:.12g}" if isinstance(value, float) else str(value)  # 12 digits: 1/6 is 0.166666666667, not 0.166667


def format_rows(table, markdown: bool = False) -> str:
    if markdown:
        lines = ["| key | default | unit | allowed | meaning |", "|---|---|---|---|---|"]
        lines += [f"| `{k.split('.')[-1]}` | {_fmt(v)} | {u} | {r} | {h} |" for k, v, u, r, h in table]
        return "\n".join(lines)
    wk = max(len(k) for k, *_ in table)
    wv = max(len(_fmt(v)) for _, v, *_ in table)
    lines = []
    section = None
    for k, v, u, r, h in table:
        head = k.rsplit(".", 1)[0] if "." in k else ""
        if head != section:
            section = head
            lines.append(f"[{head}]" if head else "")
        rule = "; ".join(s for s in (u, r) if s)
        lines.append(f"  {k:<{wk}}  {_fmt(v):<{wv}}  {h}" + (f"  [{rule}]" if rule else ""))
    return "\n".join(lines).lstrip("\n")


def run(args) -> int:
    from ..config import load_config

    cls, prefix = resolve(args.section)
    cfg = load_config(cls, args.config, args.overrides)
    print(format_rows(rows(cfg, prefix), markdown=args.markdown))
    if args.section is None and not args.markdown:
        print(f"\nmore: ti-cmax params SECTION (commands {', '.join(c for c in CONFIGS if c != 'slam')}; "
              f"sections such as rtpt, gae, smt, benchmark)")
    return 0
