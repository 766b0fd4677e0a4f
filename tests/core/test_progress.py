"""Progress bars (issue 18, point 6): rounded totals and readable units, a total for the baselines' bars, and
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
def test_quiet_silences_taichi_start_line(quiet):
    code = ("from ti_cmax import progress; progress.set_quiet(%s)\n"
            "from ti_cmax.kernels import runtime; runtime.ensure_init(); print('ok')" % quiet)
    env = {k: v for k, v in os.environ.items() if k != "TI_CMAX_NO_PROGRESS"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0 and out.stdout == "ok\n"  # stdout stays clean either way
    assert ("] Starting on arch" in out.stderr) is not quiet  # "[Taichi] ..." or "[Quadrants] ..."
