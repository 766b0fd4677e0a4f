"""Config validation at load time and discoverability: one declaration per field
drives the check, ``ti-cmax params``, the configuration page and the example config."""
import dataclasses
import re
import subprocess
import sys
from pathlib import Path

import pytest

from ti_cmax.cli import main
from ti_cmax.commands.params import CONFIGS, config_class
from ti_cmax.config import BackendConfig, FrontendConfig, SlamConfig, iter_params, load_config
from ti_cmax.errors import InputError

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("override, message", [
    ("spline_degree=2", "spline_degree must be one of 1, 3, got 2"),
    ("pano_height=-5", r"pano_height must be 0 \(derived\) or >= 8 and <= 16384 px, got -5"),
    ("dt_knots=-1", "dt_knots must be >= 0.001 s"),
    ("dt_knots=0.2", r"dt_knots must be <= backend_sliding_window_stride \(0.1 s\), got 0.2"),
    ("trajectory_rate=0", "trajectory_rate must be > 0 and <= 100000 Hz"),
    ("lambda0=0", "lambda0 must be > 0"),  # it divides
    ("realtime_chunk=100", r"realtime_chunk must be <= realtime_target_lag \(0.3 s\)"),  # a 0.6 s replay took 104 s
    ("num_events_per_packet=1000000000", "num_events_per_packet must be 0"),  # sizes memory up front (22 GB)
    ("pano_height=100000", "pano_height must be 0"),
    ("backend_time_window_size=0", "backend_time_window_size must be > 0 s"),
    ("gamma=-1", "gamma must be > 0"),
    ("gamma=.nan", r"gamma expects float \(finite\)"),
    ("backend_sliding_window_stride=0.5", "backend_sliding_window_stride must be <= backend_time_window_size"),
    ("frontend_cg_line_search_tol=1.5", "frontend_cg_line_search_tol must be > 0 and < 1"),
    ("num_threads=-2", "num_threads must be 0"),
    ("chunk_size=0", "chunk_size must be >= 1"),
    ("frontend_slicing=fixed", "frontend_slicing must be one of bounded, paper"),
    ("contrast_measure=entropy", "contrast_measure must be one of variance, mean_square"),
    ("width=240", "give both width and height, or neither"),
])
def test_bad_values_are_one_error_naming_key_and_allowed_values(override, message):
    with pytest.raises(InputError, match=message) as exc:
        load_config(SlamConfig, None, [override])
    assert str(exc.value).startswith("--set: ")


def test_zero_means_derived_or_off_where_declared():
    cfg = load_config(SlamConfig, None, ["num_events_per_packet=0", "pano_height=0", "frontend_max_packet_events=0"])
    assert cfg.frontend.num_events_per_packet == 0 and cfg.backend.pano_height == 0


def test_checks_also_apply_to_python_construction_and_yaml(tmp_path):
    with pytest.raises(InputError, match="spline_degree"):
        BackendConfig(spline_degree=2)
    with pytest.raises(InputError, match="dt_ang_vel"):
        dataclasses.replace(FrontendConfig(), dt_ang_vel=0.0)
    (tmp_path / "c.yaml").write_text("backend:\n  backend_time_window_size: 0\n")
    with pytest.raises(InputError, match=r"c.yaml: backend_time_window_size must be > 0"):
        load_config(SlamConfig, tmp_path / "c.yaml")


def test_cli_rejects_bad_config_before_work(tmp_path, capsys):
    """One line, exit 2, no traceback, nothing written (the dataset is not even opened)."""
    out = tmp_path / "out"
    assert main(["slam", str(tmp_path / "absent"), "--out", str(out), "--set", "spline_degree=2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["ti-cmax slam: error: --set: spline_degree must be one of 1, 3, got 2"]
    assert not out.exists()


def test_kernel_contrast_measures_are_the_config_choices():
    from ti_cmax.config import CONTRAST_MEASURES
    from ti_cmax.kernels.iwe import MEASURES

    assert set(MEASURES) == set(CONTRAST_MEASURES)


@pytest.mark.parametrize("command", list(CONFIGS))
def test_params_lists_every_field_of_every_config(command, capsys):
    """``ti-cmax params COMMAND`` prints each leaf key of the command's config with its default; every field is
    declared with a line of help (adding a field without one fails here)."""
    cls = config_class(command)
    assert main(["params", command]) == 0
    out = capsys.readouterr().out
    listed = {line.split()[0]: line.split()[1] for line in out.splitlines() if line.startswith("  ")}
    default = cls()
    for key, f, _ in iter_params(cls):
        assert f.metadata.get("help"), f"{cls.__name__}.{key} has no help"
        assert key in listed, key
        value = default
        for part in key.split("."):
            value = getattr(value, part)
        shown = listed[key]
        if isinstance(value, bool):
            assert shown == str(value).lower()
        elif isinstance(value, (int, float)):
            assert float(shown) == pytest.approx(value), key
    assert len(listed) == len(list(iter_params(cls)))


def test_params_section_and_config_file(capsys):
    assert main(["params", "backend", "--set", "spline_degree=1"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"backend\.spline_degree\s+1\s", out) and "frontend." not in out
    assert main(["params", "rtpt"]) == 0 and "rtpt.rtpt_packet_size" in capsys.readouterr().out
    assert main(["params", "nonsense"]) == 2
    assert "unknown section 'nonsense'" in capsys.readouterr().err
    assert main(["params", "--config", str(ROOT / "examples" / "config.yaml")]) == 0


def test_example_config_loads_and_names_real_keys():
    import yaml

    cfg = load_config(SlamConfig, ROOT / "examples" / "config.yaml")
    data = yaml.safe_load((ROOT / "examples" / "config.yaml").read_text())
    assert set(data) == {"dataset", "frontend", "backend", "output"}
    for section, values in data.items():
        for key, value in values.items():
            assert getattr(getattr(cfg, section), key) == value


def test_configuration_page_is_the_generated_reference():
    """docs/configuration.md is ``ti-cmax params --markdown``'s output: regenerate it when a config changes."""
    from ti_cmax.commands.params import reference_page

    page = (ROOT / "docs" / "configuration.md").read_text()
    assert page == reference_page(), "stale: run `ti-cmax params --markdown > docs/configuration.md`"
    assert "| `num_events_per_packet` |" in page and "## `benchmark`" in page


def test_version(capsys):
    from ti_cmax import __version__

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.startswith(f"ti-cmax {__version__}")


def test_version_imports_no_kernel_and_is_fast():
    """--version builds no subcommand's arguments: neither Taichi nor the pipelines load (it took ~2 s)."""
    import time

    code = ("import sys; from ti_cmax.cli import main\ntry:\n    main(['--version'])\nexcept SystemExit:\n    pass\n"
            "print([m for m in ('taichi', 'quadrants', 'ti_cmax.kernels.runtime', 'ti_cmax.pipelines') "
            "if m in sys.modules])")
    tic = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    elapsed = time.perf_counter() - tic
    assert out.returncode == 0 and out.stdout.splitlines()[-1] == "[]", out.stdout + out.stderr
    assert out.stdout.startswith("ti-cmax ") and elapsed < 1.0, elapsed


def test_a_command_imports_its_own_module_alone_and_version_none():
    """The command being run is the one subcommand module imported (the others are listed by name); --version
    imports none (what it prints comes from the installed metadata)."""
    code = ("import sys\nfrom ti_cmax.cli import build_parser, main\n"
            "names = lambda: sorted(m for m in sys.modules if m.startswith('ti_cmax.commands.'))\n"
            "try:\n    main(['--version'])\nexcept SystemExit as exc:\n    print(exc.code, names())\n"
            "parser = build_parser('evaluate')\n"
            "print(names(), parser.parse_args(['evaluate', '--groundtruth', 'a', '--estimate', 'b']).command)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.splitlines()[-2:] == ["0 []", "['ti_cmax.commands.evaluate'] evaluate"], out.stderr


@pytest.mark.slow
def test_closed_output_pipe_ends_quietly():
    proc = subprocess.Popen([sys.executable, "-m", "ti_cmax.cli", "params", "smt"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    proc.stdout.close()  # the reader is gone before the command writes (like `| head -0`)
    err = proc.stderr.read().decode()
    assert proc.wait() == 141 and err == ""


def test_missing_calibration_and_missing_extra_say_how(tmp_path, monkeypatch):
    from ti_cmax.io import open_dataset
    from ti_cmax.io import aedat4

    (tmp_path / "events.txt").write_text("0.0 1 2 1\n0.1 3 4 0\n")
    with pytest.raises(InputError, match="--set allow_default_calibration=true"):
        open_dataset(tmp_path).camera
    monkeypatch.setitem(sys.modules, "aedat", None)  # import aedat now raises ImportError
    with pytest.raises(InputError, match=re.escape('pip install -e ".[aedat]"')):
        aedat4._decoder(tmp_path / "x.aedat4")


def test_numpy_scalars_are_accepted_and_stored_as_python_numbers(tmp_path):
    import numpy as np

    from ti_cmax.config import save_config

    cfg = BackendConfig(pano_height=np.int64(256), dt_knots=np.float32(0.1))
    assert type(cfg.pano_height) is int and type(cfg.dt_knots) is float
    save_config(SlamConfig(backend=cfg), tmp_path / "c.yaml")  # YAML-safe
    assert load_config(SlamConfig, tmp_path / "c.yaml").backend == cfg
    with pytest.raises(InputError, match="pano_height expects int"):
        BackendConfig(pano_height=True)


def test_a_command_builds_only_its_own_arguments():
    """`ti-cmax slam` does not pay for the other commands' argument choices (the benchmark's suites import the
    baselines, simulate's import scipy, grayscale's config once imported the mapping kernels): ~0.5 s of start-up;
    nor for --version's text (importlib.metadata, ~30 ms) unless asked. Every command is still listed, and each
    one's --help still works."""
    code = ("import sys; from ti_cmax.cli import build_parser; p = build_parser('slam'); "
            "heavy = [m for m in ('ti_cmax.pipelines.evaluation.benchmark', 'ti_cmax.simulate', 'ti_cmax.pipelines.workflows.grayscale', "
            "'scipy.ndimage', 'taichi', 'quadrants', 'importlib.metadata') if m in sys.modules]; print(heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stdout + out.stderr
    for command in ("benchmark", "simulate", "grayscale", "slam"):
        with pytest.raises(SystemExit) as exc:
            main([command, "--help"])
        assert exc.value.code == 0


def test_yaml_booleans_and_numbers_do_not_pass_for_each_other(tmp_path):
    """`width: true` became 1 and `loop_closure: 2` or `[1]` became true; 0 / 1 and yes / no strings stay allowed."""
    for text, message in (("dataset:\n  width: true\n", "'dataset.width' expects int, got True"),
                          ("loop_closure: 2\n", "expects bool, got 2"), ("loop_closure: [1]\n", "expects bool")):
        path = tmp_path / "c.yaml"
        path.write_text(text)
        with pytest.raises(InputError, match=message):
            load_config(SlamConfig, path)
    assert load_config(SlamConfig, None, ["loop_closure=0"]).loop.loop_closure is False
    assert load_config(SlamConfig, None, {"loop_closure": 1}).loop.loop_closure is True
