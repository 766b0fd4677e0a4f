"""Progress bars: rounded totals and readable units, a total for the baselines' bars, and
--quiet also silences Taichi's start-up line."""
import os
import subprocess
import sys

import pytest

from ti_cmax import progress as P


@pytest.fixture
def bars_on():
    old = P.is_quiet()
    P.set_quiet(False)
    yield
    P.set_quiet(old)


def test_data_bar_rounds_and_names_the_unit(bars_on):
    bar = P.progress(total=4.946939, desc="slam", unit="s")
    for _ in range(491):
        bar.update(0.01)  # 4.909999999999938 after float accumulation
    text = str(bar)
    bar.close()
    assert "4.91/4.95 s of data" in text and "x real time" in text
    assert "4.9099" not in text and "4.946939" not in text
    open_bar = P.progress(total=None, desc="rtpt", unit="s")
    open_bar.update(1.23456)
    assert "1.23 s of data" in str(open_bar)
    open_bar.close()
    count = P.progress(total=15_500_000, desc="convert", unit="ev")
    count.update(1_234_567)
    assert "1.23M/15.5M" in str(count)
    count.close()


def test_dataset_stream_gives_the_baselines_a_total(tmp_path):
    from ti_cmax.camera import Camera
    from ti_cmax.io import open_dataset, write_calib_txt
    from ti_cmax.pipelines.baselines import CountedChunks

    (tmp_path / "events.txt").write_text("".join(f"{0.01 * i:.6f} {i % 240} {i % 180} 1\n" for i in range(1, 301)))
    write_calib_txt(tmp_path / "calib.txt", Camera(240, 180, 199.0, 199.0, 120.0, 90.0))
    ds = open_dataset(tmp_path)
    chunks = CountedChunks(ds.stream(100))
    assert chunks.span == pytest.approx(2.99)  # RTPT's and CMax-GAE's bar total
    assert sum(len(c) for c in chunks) == 300 and chunks.count == 300
    assert CountedChunks(ds.iter_events(100)).span is None  # a bare generator has no total


@pytest.mark.parametrize("quiet", [False, True])
def test_taichi_start_line_never_breaks_into_the_bars(quiet):
    code = ("from ti_cmax import progress; progress.set_quiet(%s)\n"
            "from ti_cmax.kernels import runtime; runtime.ensure_init(); print('ok')" % quiet)
    env = {k: v for k, v in os.environ.items() if k != "TI_CMAX_NO_PROGRESS"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0 and out.stdout == "ok\n"  # stdout stays clean either way
    assert "] Starting on arch" not in out.stderr  # "[Taichi] ..." or "[Quadrants] ..."


@pytest.fixture
def closed_bars(monkeypatch):
    """(description, n, total) of every bar as it closes."""
    from tqdm import tqdm

    seen = []
    original = tqdm.close

    def close(bar):
        if not getattr(bar, "_recorded", False):
            bar._recorded = True
            seen.append((getattr(bar, "desc", None), getattr(bar, "n", None), getattr(bar, "total", None)))
        original(bar)

    monkeypatch.setattr(tqdm, "close", close)
    return seen


def test_stage_bars_reach_their_totals(bars_on, closed_bars, capsys):
    with P.stage("start-up and compile"):
        pass
    with P.StageBars(2.0, ("reading", "front-end")) as bars:
        bars.start(10.0)
        bars.at("reading", 11.2)
        bars.at("front-end", 10.7)
        bars.at("front-end", 10.5)  # never backwards
        assert bars.bars["front-end"].n == pytest.approx(0.7)
        bars.done()
    assert closed_bars == [("start-up and compile", 1, 1), ("reading", 2.0, 2.0), ("front-end", 2.0, 2.0)]
    assert "100%" in capsys.readouterr().err


def test_slam_bars_one_per_stage_all_at_100(bars_on, closed_bars, short_slice, capsys):
    """run_slam: start-up and compile, reading, front-end and back-end bars, each at its total at the end (the
    first chunk and the close were not counted: the bar stopped near 50 %)."""
    from ti_cmax.config import SlamConfig
    from ti_cmax.pipelines.slam import run_slam

    events, camera = short_slice
    span = float(events.t[-1] - events.t[0])
    chunks = [events[i:i + 20000] for i in range(0, len(events), 20000)]
    run_slam(chunks, camera, SlamConfig(), progress_total=span)
    assert [d for d, _, _ in closed_bars] == ["start-up and compile", "reading", "front-end", "back-end"]
    assert all(n == pytest.approx(total) for _, n, total in closed_bars), closed_bars
    err = capsys.readouterr().err
    assert "Taichi" not in err


def test_quiet_prints_nothing(short_slice, capsys):
    from ti_cmax.config import SlamConfig
    from ti_cmax.pipelines.slam import run_slam

    old = P.is_quiet()
    P.set_quiet(True)
    try:
        events, camera = short_slice
        run_slam(events, camera, SlamConfig(), progress_total=float(events.t[-1] - events.t[0]))
    finally:
        P.set_quiet(old)
    captured = capsys.readouterr()
    assert captured.err == "" and captured.out == ""


@pytest.fixture(scope="module")
def short_slice(ti_runtime):
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence

    seq = simulate_sequence(SimulatorConfig(scene="bay", duration=0.3, max_angular_velocity=3.0, seed=3))
    return seq.events.slice_time(0.1, 0.3), seq.camera


def test_quiet_bars_import_no_tqdm_and_count_nothing_as_disabled_tqdm_bars():
    """While quiet a bar is a QuietBar (tqdm, ~0.03 s of start-up, is not imported); it counts nothing, as a disabled
    tqdm bar, and what else is asked of it a disabled tqdm bar answers."""
    code = ("import sys\n"
            "from ti_cmax import progress\n"
            "progress.set_quiet(True)\n"
            "with progress.stage('x'):\n"
            "    bar = progress.progress(total=3.0, desc='y', unit='s'); bar.update(1.0); bar.at(2.0); bar.done()\n"
            "    with progress.progress(total=10, desc='z', unit='ev') as count:\n"
            "        count.update(4)\n"
            "print(bar.n, count.n, 'tqdm' in sys.modules)\n"
            "print(bar.disable, 'tqdm' in sys.modules)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.stdout.split() == ["0", "0", "False", "True", "True"], proc.stderr
