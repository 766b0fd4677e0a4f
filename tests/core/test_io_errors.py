"""Bad inputs give one clear InputError naming the file and line (or event index); CLI info/convert smoke tests."""
from __future__ import annotations

import json

import numpy as np
import pytest

from ti_cmax.camera import Camera
from ti_cmax.cli import main
from ti_cmax.errors import InputError
from ti_cmax.events import Events
from ti_cmax.io import open_dataset, read_calib, read_tum, write_calib_txt, write_events_h5, write_events_txt
from ti_cmax.io import events_txt, h5

CAM = Camera(240, 180, 199.0, 199.0, 120.0, 90.0)
GOOD = "".join(f"{0.001 * i:.9f} {i * 37 % 240} {i * 53 % 180} {i % 2}\n" for i in range(1, 21))


def folder_with(tmp_path, text: str, calib=True):
    d = tmp_path / "seq"
    d.mkdir()
    (d / "events.txt").write_text(text)
    if calib:
        write_calib_txt(d / "calib.txt", CAM)
    return d


def read_all(path, **kw):
    return open_dataset(path, **kw).read_events()


def test_empty_file(tmp_path):
    d = folder_with(tmp_path, "# only a comment\n\n")
    with pytest.raises(InputError, match=r"events.txt: the file holds no events"):
        open_dataset(d)
    with pytest.raises(InputError, match=r"events.txt: the file holds no events"):
        open_dataset(d, 240, 180)
    write_events_h5(tmp_path / "empty.h5", Events.empty(), camera=CAM)
    with pytest.raises(InputError, match=r"empty.h5: the file holds no events"):
        open_dataset(tmp_path / "empty.h5")


@pytest.mark.parametrize("bad, line, what", [
    ("0.0105 10 x 1\n", 11, "expected 't x y p'"),
    ("0.0105 10 20\n", 11, "got 3 values"),
    ("0.0105 10 20 7\n", 11, "polarity must be 0/1 or -1/\\+1"),
    ("0.0105 -3 20 1\n", 11, "pixel coordinates must be finite and >= 0"),
    ("nan 10 20 1\n", 11, "not a finite number"),
    ("0.0001 10 20 1\n", 11, "not sorted"),
])
def test_bad_line_is_named(tmp_path, bad, line, what):
    lines = GOOD.splitlines(keepends=True)
    d = folder_with(tmp_path, "".join(lines[:10]) + bad + "".join(lines[10:]))
    with pytest.raises(InputError, match=rf"events.txt, line {line}: .*{what}"):
        read_all(d, width=240, height=180)


def test_line_numbers_count_comments_and_blank_lines(tmp_path):
    lines = GOOD.splitlines(keepends=True)
    text = "# header\n\n" + "".join(lines[:5]) + "0.0055 250 3 1\n" + "".join(lines[5:])
    with pytest.raises(InputError, match=r"line 8: x=250 is outside the sensor \(expected 0 <= x < 240\)"):
        read_all(folder_with(tmp_path, text), width=240, height=180)


def test_unsorted_across_block_border(tmp_path, monkeypatch):
    n = 4000
    t = np.arange(n) * 1e-4
    t[2500] = t[100]  # far from the first block, which is small
    ev = Events(t, np.zeros(n, np.uint16), np.zeros(n, np.uint16), np.ones(n, np.int8))
    d = tmp_path / "seq"
    d.mkdir()
    write_events_txt(d / "events.txt", ev)
    write_calib_txt(d / "calib.txt", CAM)
    monkeypatch.setattr(events_txt, "BLOCK_BYTES", 2000)
    with pytest.raises(InputError, match=r"line 2501: timestamps are not sorted"):
        read_all(d, width=240, height=180)
    # the same across HDF5 slices: the error names the event index
    monkeypatch.setattr(h5, "BLOCK_EVENTS", 1000)
    t2 = np.arange(n) * 1e-4
    t2[2000] = 0.0  # first event of the third slice goes back in time
    write_events_h5(tmp_path / "ev.h5", Events(t2, ev.x, ev.y, ev.p), camera=CAM)
    with pytest.raises(InputError, match=r"ev.h5: event 2000: timestamps are not sorted"):
        read_all(tmp_path / "ev.h5")


def test_x_outside_sensor_h5(tmp_path):
    ev = Events(np.arange(5) * 1.0, np.array([1, 2, 240, 3, 4]), np.zeros(5), np.ones(5))
    write_events_h5(tmp_path / "ev.h5", ev, camera=CAM)
    with pytest.raises(InputError, match=r"ev.h5: event 2: x=240 is outside the sensor"):
        read_all(tmp_path / "ev.h5")


def test_missing_and_malformed_calibration(tmp_path):
    d = folder_with(tmp_path, GOOD, calib=False)
    ds = open_dataset(d)  # events are readable without intrinsics
    assert len(ds.read_events()) == 20 and ds.calibration_source is None
    with pytest.raises(InputError, match="no camera calibration"):
        ds.camera
    assert open_dataset(d, allow_default_calibration=True).camera == Camera.ideal(240, 180, 60.0)
    (d / "calib.txt").write_text("# intrinsics\n199 199 120 90 0.1\n")
    with pytest.raises(InputError, match=r"calib.txt, line 2: expected 'fx fy cx cy .*got 5 values"):
        open_dataset(d)
    (d / "calib.txt").write_text("199 199 abc 90\n")
    with pytest.raises(InputError, match=r"calib.txt, line 1: expected"):
        read_calib(d / "calib.txt", 240, 180)
    (d / "calib.txt").write_text("")
    with pytest.raises(InputError, match=r"calib.txt: calibration file is empty"):
        read_calib(d / "calib.txt", 240, 180)
    (d / "calib.txt").unlink()
    (d / "camera_info.yaml").write_text("image_width: 240\ncamera_matrix: {data: [1, 2]}\n")
    with pytest.raises(InputError, match=r"camera_info.yaml: malformed camera_info YAML"):
        open_dataset(d)


def test_truncated_and_wrong_hdf5(tmp_path):
    n = 50_000
    ev = Events(np.arange(n) * 1e-5, np.zeros(n), np.zeros(n), np.ones(n))
    path = write_events_h5(tmp_path / "ev.h5", ev, camera=CAM)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=r"ev.h5: cannot (open as HDF5|read the HDF5 structure) \(truncated"):
        open_dataset(path)
    import h5py

    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["images"] = np.zeros(3)
    with pytest.raises(InputError, match=r"other.h5: no events found: expected datasets events/\{t,x,y,p\}"):
        open_dataset(tmp_path / "other.h5")


def test_other_text_files(tmp_path):
    (tmp_path / "gt.txt").write_text("# t tx ty tz qx qy qz qw\n0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0\n")
    with pytest.raises(InputError, match=r"gt.txt, line 3: expected 8 values"):
        read_tum(tmp_path / "gt.txt")
    with pytest.raises(InputError, match=r"unsupported events file type '.csv'"):
        open_dataset((tmp_path / "ev.csv"), 240, 180) if (tmp_path / "ev.csv").write_text("x") else None
    with pytest.raises(InputError, match="no such file or folder"):
        open_dataset(tmp_path / "missing")


# CLI ----------------------------------------------------------------------------------------------
def test_cli_info_and_convert(tmp_path, capsys):
    d = folder_with(tmp_path, GOOD)
    assert main(["info", str(d)]) == 0
    out = capsys.readouterr().out
    assert "events        20" in out and "240 x 180" in out and "fx=199.0000" in out and "IMU           none" in out
    assert main(["info", str(d), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["num_events"] == 20 and info["duration_s"] == pytest.approx(0.019)
    assert info["calibration"]["source"] == "calib.txt" and info["groundtruth"] is None

    out_h5 = tmp_path / "out" / "ev.h5"
    assert main(["convert", str(d), str(out_h5), "--quiet"]) == 0
    back = open_dataset(out_h5)
    assert back.camera == CAM
    np.testing.assert_allclose(back.read_events().t, open_dataset(d).read_events().t, atol=0)
    assert main(["info", str(out_h5), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["calibration"]["source"] == "HDF5 file"
    # time cut, and the text output form
    assert main(["convert", str(out_h5), str(tmp_path / "cut.txt"), "--t-start", "0.005", "--t-end", "0.010"]) == 0
    assert len((tmp_path / "cut.txt").read_text().splitlines()) == 5


def test_cli_bad_input_leaves_no_output(tmp_path, capsys):
    lines = GOOD.splitlines(keepends=True)
    d = folder_with(tmp_path, "".join(lines[:15]) + "garbage here\n" + "".join(lines[15:]))
    out = tmp_path / "res" / "ev.h5"
    for size in ([], ["--width", "240", "--height", "180"]):  # error while opening / while streaming
        assert main(["convert", str(d), str(out), *size]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith("ti-cmax convert: error: ") and "events.txt, line 16" in err[-1]
        assert not out.exists()
    assert not out.parent.exists()  # the temporary file is gone too, and the folder made for it
    assert main(["info", str(tmp_path / "nothing")]) == 2
    assert "no such file or folder" in capsys.readouterr().err


def test_cli_convert_failures_leave_nothing(tmp_path, capsys):
    n = 3000
    ev = Events(np.arange(n) * 1e-4, np.zeros(n), np.zeros(n), np.ones(n))
    unsorted = Events(ev.t[::-1].copy(), ev.x, ev.y, ev.p)
    write_events_h5(tmp_path / "unsorted.h5", unsorted, camera=CAM)
    trunc = write_events_h5(tmp_path / "trunc.h5", ev, camera=CAM)
    trunc.write_bytes(trunc.read_bytes()[:-4000])
    (tmp_path / "empty.txt").write_text("")
    for src, msg in (("unsorted.h5", "not sorted"), ("trunc.h5", "truncated"), ("empty.txt", "no events")):
        out = tmp_path / "out" / f"{src}.h5"
        assert main(["convert", str(tmp_path / src), str(out), "--width", "240", "--height", "180"]) == 2
        assert msg in capsys.readouterr().err
        assert not out.exists()
    assert not (tmp_path / "out").exists() or list((tmp_path / "out").iterdir()) == []


@pytest.mark.parametrize("name, lib", [("x.bag", "rosbags"), ("x.aedat4", "aedat")])
def test_garbage_bag_and_aedat4(tmp_path, name, lib):
    pytest.importorskip(lib)
    (tmp_path / name).write_bytes(b"not a recording\n" * 10)
    with pytest.raises(InputError, match=rf"{name}: cannot open"):
        open_dataset(tmp_path / name)


@pytest.mark.parametrize("bad, line, what", [
    ("0.0005 3 3 1\n", 6, "timestamps are not sorted"),
    ("nan 3 3 1\n", 6, "timestamp is not a finite number"),
    ("0.0055 241 3 1\n", 6, "x=241 is outside the sensor"),
])
def test_info_checks_what_it_reads(tmp_path, capsys, bad, line, what):
    """info streams the events through the readers' checks: exit 2 naming the line, not a fine-looking summary.
    The pixel check uses the sensor size of calib.txt's second line ('240 180', as some ECD copies have)."""
    lines = GOOD.splitlines(keepends=True)
    d = folder_with(tmp_path, "".join(lines[:5]) + bad + "".join(lines[5:]))
    (d / "calib.txt").write_text("199 199 120 90\n240 180\n")
    assert main(["info", str(d)]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"events.txt, line {line}: {what}" in err
    assert main(["info", str(d), "--no-check", "--json"]) == 0  # the cheap summary does not read the events
    assert json.loads(capsys.readouterr().out)["events_checked"] is False


def test_info_sensor_size_sources(tmp_path, capsys):
    d = folder_with(tmp_path, GOOD)
    assert main(["info", str(d)]) == 0
    out = capsys.readouterr().out
    assert "inferred from pixel coordinates: the smallest known sensor" in out and "--set width=W" in out
    assert "checked       timestamps finite and sorted" in out
    (d / "calib.txt").write_text("199 199 120 90\n346 260\n")
    assert main(["info", str(d), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["sensor"] == {"width": 346, "height": 260, "from": "calib.txt, line 2"}
    assert main(["info", str(d), "--json", "--set", "width=240", "--set", "height=180"]) == 0
    assert json.loads(capsys.readouterr().out)["sensor"]["from"] == "given"
    (d / "calib.txt").write_text("199 199 120 90\n346 x\n")
    assert main(["info", str(d)]) == 2
    assert "calib.txt, line 2: expected the sensor size 'width height'" in capsys.readouterr().err


def test_odd_calibrations_and_attributes_are_one_clear_error(tmp_path):
    """Found by fuzzing: a NaN principal point (camera_info YAML, HDF5 attributes) and distortion coefficients that
    fold over inside the sensor were accepted (a trajectory 40 deg off with status ok, or a crash later); malformed
    HDF5 attributes and a non-list distortion gave tracebacks. Real distortion keeps its bitwise table."""
    import h5py

    with pytest.raises(InputError, match="must be finite"):
        Camera(240, 180, 200.0, 200.0, float("nan"), 89.5)
    for dist in ((-3.0, -20.0, 0, 0, 0), (50.0, 0, 0, 0, 0), (0, 0, 2.0, 2.0, 0)):
        with pytest.raises(InputError, match="cannot be inverted over the sensor"):
            Camera(240, 180, 199.0, 199.0, 119.5, 89.5, dist).bearing_lut
    real = Camera(240, 180, 199.09, 198.83, 132.19, 110.71, (-0.368, 0.151, -0.0003, -0.00076, 0.0))
    ys, xs = np.mgrid[0:180, 0:240]
    assert np.array_equal(real.bearing_lut, real.unproject(xs.ravel(), ys.ravel()).astype(np.float32))

    yaml_path = tmp_path / "camera_info.yaml"
    yaml_path.write_text("image_width: 240\nimage_height: 180\n"
                         "camera_matrix: {data: [200, 0, 120, 0, 200, 90, 0, 0, 1]}\ndistortion_coefficients: abc\n")
    with pytest.raises(InputError, match="malformed camera_info YAML"):
        read_calib(yaml_path)
    n = 100
    for attrs in ({"sensor_resolution": [180]}, {"t_offset": np.array([], np.int64)}):
        path = tmp_path / "events.h5"
        with h5py.File(path, "w") as f:
            for k, v in (("t", np.arange(n, dtype=np.int64)), ("x", np.zeros(n, np.uint16)),
                         ("y", np.zeros(n, np.uint16)), ("p", np.ones(n, np.int8))):
                f[f"events/{k}"] = v
            f.attrs.update({"width": 240, "height": 180} if "t_offset" in attrs else {}, **attrs)
        with pytest.raises(InputError, match="malformed attribute"):
            open_dataset(path)


def test_cli_refuses_bad_arguments_and_config_files(tmp_path, capsys):
    """--threads -3 (a Taichi C++ error), --config naming a folder or a non-UTF-8 file, map --gamma 0 (an all-black
    PNG with exit 0): one usage or input error each."""
    (tmp_path / "folder").mkdir()
    binary = tmp_path / "bad.yaml"
    binary.write_bytes(b"\xff\xfe\x00bad")
    with pytest.raises(SystemExit) as exc:
        main(["params", "--threads", "-3"])
    assert exc.value.code == 2 and "expected a thread count" in capsys.readouterr().err
    for cfg in (tmp_path / "folder", binary):
        assert main(["params", "--config", str(cfg)]) == 2
        assert "cannot read the config file" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["map", "x", "--trajectory", "t.txt", "--out", str(tmp_path / "m.png"), "--gamma", "0"])
    assert exc.value.code == 2 and "expected a finite number > 0" in capsys.readouterr().err
    for bad in (["--scene", "bogus"], ["--duration", "-1"]):  # refused before the sequence folder is made
        with pytest.raises(SystemExit) as exc:
            main(["sweep", "--out", str(tmp_path / "sweep"), "--quick", *bad])
        assert exc.value.code == 2 and not (tmp_path / "sweep").exists()
    capsys.readouterr()


def test_map_sizes_the_pipelines_would_refuse_are_one_error_naming_the_option(tmp_path, capsys):
    """Found by fuzzing: `map --size 2x1` (or 40000x20000) rendered a panorama with exit 0, past the back-end's own
    bounds (pano_width 16..32768, pano_height 8..16384 px); grayscale's 3x2 failed later without naming --size;
    super-resolution's --sizes 65536x32768 named pano_height, once the smaller sizes had run."""
    d = folder_with(tmp_path, GOOD)
    traj = tmp_path / "traj.txt"
    traj.write_text("0 0 0 0 0 0 0 1\n0.05 0 0 0 0 0 0 1\n")
    png = tmp_path / "out" / "m.png"
    cases = [(["map", "--size", "2x1"], "--size 2x1: the map width must be >= 16 and <= 32768 px (as pano_width)"),
             (["map", "--size", "16x7"], "--size 16x7: the map height must be >= 8 and <= 16384 px"),
             (["map", "--size", "40000x20000"], "--size 40000x20000: the map width must be >= 16 and <= 32768"),
             (["grayscale", "--size", "3x2"], "--size 3x2: the map width must be >= 4 px (as pano_width), got 3"),
             (["grayscale", "--sizes", "64x32,4x1"], "--sizes 4x1: the map height must be >= 2 px")]
    for (command, *size), message in cases:
        assert main([command, str(d), "--trajectory", str(traj), "--out", str(png), *size, "--quiet"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and message in err, err
        assert not png.parent.exists()
    for sizes in ("8x4", "65536x32768", "512x256,33000x16500"):
        assert main(["super-resolution", str(d), "--out", str(png.parent), "--sizes", sizes, "--quiet"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"--sizes {sizes.split(',')[-1]}: the map " in err, err
        assert not png.parent.exists()


def test_a_lost_worker_is_one_error_line(monkeypatch, capsys):
    """A back-end worker killed from outside (out of memory) gave a RuntimeError traceback: one line, exit 1."""
    from ti_cmax.commands import params
    from ti_cmax.errors import WorkerLost

    def lost(args):
        raise WorkerLost("the back-end process ended without a result (exit -9: killed or out of memory?)")

    monkeypatch.setattr(params, "run", lost)
    assert main(["params"]) == 1
    err = capsys.readouterr().err
    assert "error: the back-end process ended" in err and "Traceback" not in err
