"""Live view of a CMax-SLAM run in rerun (``pip install -e ".[viewer]"``): ``ti-cmax slam ... --viewer`` and
``--save-recording FILE.rrd``, or in the API as OnlineSlam's observer::

    viewer = RerunViewer(camera, config, spawn=True)           # or save="run.rrd"
    online = OnlineSlam(camera, config, on_packet=viewer.on_packet, on_window=viewer.on_window)
    viewer.attach(online)
    for chunk in stream: online.push(chunk)
    viewer.finish(online.close())

What it logs, on the timeline ``sensor_time`` (seconds of data):

* ``camera/iwe``: the image of warped events of each front-end packet at its angular velocity (the sharp image the
  front-end maximised; events dark on white), every ``iwe_every`` packets;
* ``map``: the panoramic map of the events settled so far (cropped to the observed region and contrast-stretched,
  pipelines/panorama.map_image), at most every ``map_every`` seconds of data, and the final map;
* ``angular_velocity/{x,y,z}`` (rad/s, camera frame) per packet and ``orientation/{roll,pitch,yaw}`` (deg, Euler
  xyz of R_world_from_camera) at each packet's time, from the best estimate so far.

Its default layout (``blueprint``): the packet IWE and the map side by side above one plot of the angular velocity
and one of the orientation (the viewer's own heuristic gives each scalar its own plot and may leave one out), each
plot's three lines in red, green and blue (``SERIES_COLORS``).
"""
from __future__ import annotations

import numpy as np

from .errors import InputError

TIMELINE = "sensor_time"
# one colour per axis, told apart in each plot (x/roll red, y/pitch green, z/yaw blue)
SERIES_COLORS = {"angular_velocity/x": 0xD62728, "angular_velocity/y": 0x2CA02C, "angular_velocity/z": 0x1F77B4,
                 "orientation/roll": 0xD62728, "orientation/pitch": 0x2CA02C, "orientation/yaw": 0x1F77B4}
MAX_MAP_WIDTH = 2048  # larger maps are logged downsampled (a 8192-wide map per window made recordings of GBs)


def _rerun():
    try:
        import rerun as rr
    except ImportError:
        raise InputError('the viewer needs rerun: pip install -e ".[viewer]" (rerun-sdk)') from None
    return rr


def packet_iwe(camera, events, omega: np.ndarray, t_ref: float) -> np.ndarray:
    """Image of warped events (H, W) float32: each event rotated to ``t_ref`` at angular velocity ``omega`` and
    counted at its nearest pixel (the front-end's model; undistorted pinhole)."""
    from scipy.spatial.transform import Rotation

    h, w = camera.height, camera.width
    img = np.zeros((h, w), np.float32)
    if len(events) == 0:
        return img
    b = camera.bearings(events.x, events.y, dtype=np.float64)
    rot = Rotation.from_rotvec(np.outer(np.asarray(events.t, np.float64) - t_ref, omega))
    x = rot.apply(b)
    uv = camera.project(x[x[:, 2] > 1e-6], distort=False)
    ui, vi = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
    inside = (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    np.add.at(img, (vi[inside], ui[inside]), 1.0)
    return img


def blueprint():
    """The default layout: the images on top, the three angular velocities in one plot and the three Euler angles in
    another below, the side panels collapsed (they open from the viewer's top bar)."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(rrb.Spatial2DView(origin="camera/iwe", name="packet IWE"),
                           rrb.Spatial2DView(origin="map", name="map so far"), column_shares=[1, 2]),
            rrb.Horizontal(rrb.TimeSeriesView(origin="angular_velocity", name="angular velocity (rad/s)"),
                           rrb.TimeSeriesView(origin="orientation", name="orientation (deg)")),
            row_shares=[3, 2]),
        rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=TIMELINE))


class RerunViewer:
    """Streams a run to the rerun viewer (``spawn``), a recording file (``save``), or both."""

    def __init__(self, camera, config=None, *, spawn: bool = False, save=None, iwe_every: int = 1,
                 map_every: float = 0.25, application_id: str = "ti-cmax"):
        rr = _rerun()
        self.rr = rr
        self.camera = camera
        self.gamma = config.output.gamma if config is not None else 0.75
        self.rec = rr.RecordingStream(application_id)
        if save is not None:
            self.rec.save(str(save), default_blueprint=blueprint())
        if spawn:
            self.rec.spawn(default_blueprint=blueprint())
        for path, rgb in SERIES_COLORS.items():
            self.rec.log(path, rr.SeriesLines(colors=[(rgb << 8) | 0xFF], names=path.rsplit("/", 1)[1]), static=True)
        self.iwe_every = max(1, int(iwe_every))
        self.map_every = float(map_every)
        self.online = None
        self.packets = 0
        self._map_logged_at: float | None = None
        self._map_due: float | None = None

    def attach(self, online) -> None:
        """The OnlineSlam whose poses and map are logged (set after creating it with this viewer's callbacks)."""
        self.online = online

    def _at(self, t: float) -> None:
        self.rec.set_time(TIMELINE, duration=float(t))

    def on_packet(self, packet, omega) -> None:
        """OnlineSlam's ``on_packet``: the packet's IWE, its angular velocity and the orientation there."""
        rr = self.rr
        t = float(packet.t_ref)
        self._at(t)
        for axis, value in zip("xyz", np.asarray(omega, dtype=float)):
            self.rec.log(f"angular_velocity/{axis}", rr.Scalars(value))
        if self.online is not None:
            from scipy.spatial.transform import Rotation

            angles = np.degrees(Rotation.from_matrix(self.online.pose(t)[0]).as_euler("xyz"))
            for name, value in zip(("roll", "pitch", "yaw"), angles):
                self.rec.log(f"orientation/{name}", rr.Scalars(value))
        if self._map_due is not None and self.online is not None:
            self._map_logged_at, self._map_due = self._map_due, None
            self._log_map(self._map_logged_at, self.online.map())
            self._at(t)
        if self.packets % self.iwe_every == 0:
            from .pipelines.panorama import map_to_uint8

            iwe = packet_iwe(self.camera, packet.events, np.asarray(omega, dtype=float), t)
            peak = float(np.percentile(iwe[iwe > 0], 99)) if np.any(iwe > 0) else None
            self.rec.log("camera/iwe", rr.Image(map_to_uint8(iwe, self.gamma, peak=peak)))
        self.packets += 1

    def on_window(self, report) -> None:
        """OnlineSlam's ``on_window``: the growing map is due, at most every ``map_every`` seconds of data. It is
        fetched at the next packet: here OnlineSlam may be reading its worker's messages, and ``map()`` reads them
        too."""
        t = float(report.t_end)
        if self._map_logged_at is None or t - self._map_logged_at >= self.map_every:
            self._map_due = t

    def _log_map(self, t: float, image: np.ndarray) -> None:
        from .pipelines.panorama import map_image

        self._at(t)
        step = max(1, int(np.ceil(image.shape[1] / MAX_MAP_WIDTH)))
        if step > 1:  # block sums keep every event's weight
            h, w = image.shape[0] // step * step, image.shape[1] // step * step
            image = image[:h, :w].reshape(h // step, step, w // step, step).sum(axis=(1, 3))
        png, _ = map_image(image, self.gamma)
        self.rec.log("map", self.rr.Image(png))

    def finish(self, result) -> None:
        """The final map at the end of the trajectory; flushes the recording."""
        self._log_map(float(result.trajectory.t_end), result.map)
        self.rec.flush()
        if hasattr(self.rec, "disconnect"):
            self.rec.disconnect()


__all__ = ["RerunViewer", "blueprint", "packet_iwe", "TIMELINE"]
