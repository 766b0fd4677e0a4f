"""The live view (rerun): ``slam --save-recording`` writes a recording that reads back with each packet's angular
velocity, orientation and image of warped events, and the growing map, laid out by its own default blueprint; the IWE
of a packet is sharp at its omega."""
import numpy as np
import pytest

rr = pytest.importorskip("rerun")


def read_recording(path) -> dict:
    """{entity path: [(sensor time s, value)]}: a scalar's value, an image's (width, height)."""
    chunk = pytest.importorskip("rerun.chunk")
    out: dict = {}
    for c in chunk.RrdReader(path).stream():
        batch = c.to_record_batch()
        names = batch.schema.names
        if "sensor_time" not in names:
            continue
        times = [v.value / 1e9 for v in batch.column("sensor_time")]  # duration[ns]
        if "Scalars:scalars" in names:
            values = [v[0] for v in batch.column("Scalars:scalars").to_pylist()]
        elif "Image:format" in names:
            values = [(f[0]["width"], f[0]["height"]) for f in batch.column("Image:format").to_pylist()]
        else:
            continue
        out.setdefault(c.entity_path.lstrip("/"), []).extend(zip(times, values))
    return {k: sorted(v) for k, v in out.items()}


def read_layout(path) -> tuple[set, dict]:
    """The origins of the default blueprint's views, and {entity path: line colour} of the plotted series."""
    chunk = pytest.importorskip("rerun.chunk")
    reader = chunk.RrdReader(path)
    origins = set()
    for store in reader.blueprints():
        for c in reader.stream(store=store):
            batch = c.to_record_batch()
            if "ViewBlueprint:space_origin" in batch.schema.names:
                origins.update(o[0] for o in batch.column("ViewBlueprint:space_origin").to_pylist())
    colors = {}
    for c in reader.stream():
        batch = c.to_record_batch()
        if "SeriesLines:colors" in batch.schema.names:
            colors[c.entity_path.lstrip("/")] = batch.column("SeriesLines:colors").to_pylist()[0][0]
    return origins, colors


def test_slam_save_recording_reads_back(tmp_path, ti_runtime):
    from scipy.spatial.transform import Rotation

    from ti_cmax.cli import main
    from ti_cmax.io import read_tum

    seq, out, rrd = tmp_path / "seq", tmp_path / "out", tmp_path / "run.rrd"
    assert main(["simulate", str(seq), "--duration", "0.4", "--format", "h5", "--scene", "bay", "--quiet"]) == 0
    assert main(["slam", str(seq), "--out", str(out), "--save-recording", str(rrd), "--sequential", "--quiet"]) == 0
    got = read_recording(rrd)
    assert {"angular_velocity/x", "angular_velocity/y", "angular_velocity/z", "orientation/roll",
            "orientation/pitch", "orientation/yaw", "camera/iwe", "map"} <= set(got)
    omega = np.loadtxt(out / "angular_velocity.txt")
    assert len(got["angular_velocity/x"]) == len(omega) > 10
    for i, axis in enumerate("xyz"):
        t, w = np.array(got[f"angular_velocity/{axis}"]).T
        np.testing.assert_allclose(t, omega[:, 0], atol=1e-6)
        np.testing.assert_allclose(w, omega[:, 1 + i], atol=1e-6)
    assert got["camera/iwe"][0][1] == (240, 180)  # DAVIS240C
    maps = got["map"]
    assert len(maps) >= 2 and all(w > 10 and h > 10 for _, (w, h) in maps)
    # the orientation logged live is the estimate so far; the final trajectory differs by the BA's corrections
    traj = read_tum(out / "trajectory.txt")
    t_yaw, yaw = np.array(got["orientation/yaw"]).T
    final = np.degrees(Rotation.from_matrix(traj.at(t_yaw)).as_euler("xyz"))[:, 2]
    assert np.max(np.abs(yaw - final)) < 2.0 and np.ptp(final) > 5.0
    # one view per kind: both images, all three angular velocities in one plot, all three angles in another
    origins, colors = read_layout(rrd)
    assert origins == {"camera/iwe", "map", "angular_velocity", "orientation"}
    for plot in ("angular_velocity/", "orientation/"):
        assert len({rgba for path, rgba in colors.items() if path.startswith(plot)}) == 3, colors


def test_packet_iwe_is_sharpest_at_the_packet_omega(ti_runtime):
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence
    from ti_cmax.viewer import packet_iwe

    seq = simulate_sequence(SimulatorConfig(scene="bay", duration=0.45, max_angular_velocity=3.0, seed=3))
    ev = seq.events.slice_time(0.38, 0.43)  # 50 ms: a blur of several pixels without warping
    t_ref = 0.405
    i = np.searchsorted(seq.groundtruth.t, t_ref)
    r0, r1 = seq.groundtruth.R[i - 1], seq.groundtruth.R[i + 1]
    from ti_cmax import so3

    omega = so3.log(r0.T @ r1) / (seq.groundtruth.t[i + 1] - seq.groundtruth.t[i - 1])
    sharp = packet_iwe(seq.camera, ev, omega, t_ref)
    blurred = packet_iwe(seq.camera, ev, np.zeros(3), t_ref)
    reversed_ = packet_iwe(seq.camera, ev, -omega, t_ref)
    assert len(ev) > 10000 and np.linalg.norm(omega) > 1.0
    assert sharp.sum() == pytest.approx(blurred.sum(), rel=0.05)
    assert np.var(sharp) > 1.5 * np.var(blurred) > 1.5 * 1.5 * np.var(reversed_)


def test_viewer_without_rerun_says_how_to_install(monkeypatch):
    import sys

    from ti_cmax.errors import InputError
    from ti_cmax.viewer import RerunViewer

    monkeypatch.setitem(sys.modules, "rerun", None)
    with pytest.raises(InputError, match=r"\.\[viewer\]"):
        RerunViewer(None)
