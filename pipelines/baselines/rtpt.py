"""RTPT baseline (Reinbacher, Munda, Pock, ICCP 2017): packet-wise Gauss-Newton tracking on a probabilistic edge map.

Per packet of ``rtpt_packet_size`` events (one rotation per packet, at its mid-time):
1. prediction: R_pred = R_prev exp(v dt), v the mean angular velocity over the last ``rtpt_velocity_window``
   seconds of estimates (constant velocity; a single packet spans < 1 ms at high event rates, and the velocity of
   one packet amplifies its tracking noise into the next prediction until tracking oscillates and diverges);
2. tracking: ``rtpt_iterations`` Levenberg-Marquardt steps (damping ``rtpt_lambda``) on Eq. (4),
   1/2 sum (1 - M(pi(R b_k)))^2, each step adding ``rtpt_acceleration`` times the previous step (momentum), in
   one Taichi launch (``kernels.rtpt.track``);
3. quality monitor: q = mean edge-map value at the tracked events. q_ref is a slow running mean of q over good
   packets; a packet is bad when q < rtpt_quality_ratio * q_ref. Bad packets do not update the map; tracking is
   declared lost (status "lost", lost_at = time of the first bad packet of the streak, trajectory cut there) after
   ``rtpt_lost_seconds`` of consecutive bad packets;
4. mapping (good packets only): O += bilinear votes of the tracked events, N += 1 at every map point in the
   camera's field of view (pinhole projection of the map point into the sensor rectangle; distortion ignored for
   this count). M = min(O / N, 1). N counts packets, O events, so M is the mean number of events a map point
   triggers per packet in which it is visible, clipped to a probability.

The map does not wrap in longitude (like the original's bounded map): once the camera's view reaches the map's
left/right border (looking backwards, lon = +-180 deg) its events read M = 0, the quality drops, map updates stop and
tracking is lost, the failure mode described in the paper (Sec. IV-C1).
The first ``rtpt_bootstrap_packets`` packets always update the map (the first one at the identity, untracked).
Unlike the original, which keeps every event (Sec. II-E), the input is streamed packet by packet: memory is the map
plus one input chunk.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from ti_cmax import so3
from ti_cmax.config import Params, param
from ti_cmax.errors import InputError
from ti_cmax.progress import progress
from ti_cmax.trajectory import Trajectory
from ti_cmax.kernels.baselines import rtpt as K

from ti_cmax.pipelines.frontend import downsampled, fixed_count_packets
from .result import BaselineResult, CountedChunks


@dataclass(frozen=True)
class RTPTConfig(Params):
    """RTPT (Kim et al. 2016): defaults of the public code where it has them."""

    rtpt_packet_size: int = param(1500, "events per packet", unit="events", ge=10)
    rtpt_iterations: int = param(10, "LM iterations per packet", ge=0)
    rtpt_lambda: float = param(100.0, "LM damping", ge=0)
    rtpt_acceleration: float = param(0.4, "momentum of the LM steps", ge=0, lt=1)
    rtpt_pano_height: int = param(512, "edge map height (width = 2 x height)", unit="px", ge=8)
    rtpt_event_sample_rate: int = param(1, "keep 1 of Q events", ge=1)
    rtpt_bootstrap_packets: int = param(20, "packets that always update the map", ge=0)
    rtpt_quality_ratio: float = param(0.5, "bad packet: quality below this fraction of the running reference",
                                      ge=0, le=1)
    rtpt_quality_memory: float = param(0.02, "weight of a new good packet in the running reference", gt=0, le=1)
    rtpt_lost_seconds: float = param(0.1, "consecutive bad time that declares the track lost", unit="s", gt=0)
    rtpt_velocity_window: float = param(0.01, "past estimates that give the constant-velocity prediction", unit="s",
                                        gt=0)


def _compile(camera, dtype=np.float32) -> float:
    tic = time.perf_counter()
    b = np.array([[0.0, 0.0, 1.0]] * 4, dtype)
    O = np.zeros((8, 16), dtype)
    N = np.ones((8, 16), dtype)
    K.track(b, np.eye(3), O, N, 1)
    K.update_map(b, np.eye(3), O, N, camera.K, camera.width, camera.height, (0, 8, 0, 16))
    return time.perf_counter() - tic


def _rtpt_result(cfg: RTPTConfig, chunks: CountedChunks, times: list, rots: list, quality: list, lost_at,
                 updates: int, O: np.ndarray, N: np.ndarray, wall0: float, tic: float, compile_s: float):
    """BaselineResult of a run: the poses before the quality dropped (all of them unless lost), the edge map and
    the report (wall0 / tic: start of the run / of the tracking)."""
    if len(quality) < 2:
        raise InputError(f"RTPT needs at least 2 packets of {cfg.rtpt_packet_size} events (after keeping 1 of "
                         f"{cfg.rtpt_event_sample_rate}), got {chunks.count} events")
    seconds = time.perf_counter() - tic
    times = np.asarray(times)
    rots = np.asarray(rots)
    if lost_at is not None:  # keep the poses before the quality dropped
        keep = times < lost_at
        keep[:2] = True
        times, rots = times[keep], rots[keep]
    n_read = chunks.count
    report = {
        "status": "ok" if lost_at is None else "lost",
        "method": "rtpt",
        "events_processed": int(n_read),
        "packets": int(len(quality)),
        "map_updates": int(updates),
        "mean_quality": float(np.mean(quality)) if quality else 0.0,
        "wall_seconds": time.perf_counter() - wall0,
        "compile_seconds": compile_s,
        "us_per_event": {"frontend": seconds * 1e6 / max(n_read, 1)},
        "parameters": asdict(cfg),
    }
    if lost_at is not None:
        report["lost_at"] = float(lost_at)
    return BaselineResult(Trajectory(times, rots), K.edge_map(O, N), report)


def run_rtpt(events_or_chunks, camera, config=None, imu=None):
    """RTPT on events (Events, chunks or a dataset, streamed) -> BaselineResult (trajectory at packet mid-times,
    edge map). Reading stops where tracking is lost."""
    cfg = config.rtpt if config is not None else RTPTConfig()
    wall0 = time.perf_counter()
    chunks = CountedChunks(events_or_chunks)
    packets = fixed_count_packets(downsampled(chunks, cfg.rtpt_event_sample_rate), cfg.rtpt_packet_size)
    compile_s = _compile(camera)
    tic = time.perf_counter()
    h = int(cfg.rtpt_pano_height)
    w = 2 * h
    O = np.zeros((h, w), np.float32)
    N = np.zeros((h, w), np.float32)
    kmat = camera.K
    rays = K.view_border_rays(kmat, camera.width, camera.height)
    R = np.eye(3)
    v = np.zeros(3)
    t_prev = None
    q_ref = None
    bad_since = None
    lost_at = None
    times, rots, quality = [], [], []
    jv = 0
    updates = 0
    bar = progress(total=chunks.span, desc="rtpt", unit="s")
    try:
        for i, packet in enumerate(packets):  # streamed: memory holds one input chunk and one packet
            b = camera.bearings(packet.x, packet.y)
            tm = 0.5 * (float(packet.t[0]) + float(packet.t[-1]))
            if i == 0:
                r_est, q = np.eye(3), 1.0
            else:
                dt = tm - t_prev
                r_pred = R @ so3.exp(v * dt)
                r_est, _, _, q = K.track(b, r_pred, O, N, cfg.rtpt_iterations, cfg.rtpt_lambda,
                                         cfg.rtpt_acceleration)
                while jv + 1 < len(times) and times[jv + 1] <= tm - cfg.rtpt_velocity_window:
                    jv += 1  # latest estimate at least one velocity window old
                if tm > times[jv]:
                    v = so3.log(rots[jv].T @ r_est) / (tm - times[jv])
            bootstrap = i < cfg.rtpt_bootstrap_packets
            good = bootstrap or q_ref is None or q >= cfg.rtpt_quality_ratio * q_ref
            if i > 0 and good:
                q_ref = q if q_ref is None else (1 - cfg.rtpt_quality_memory) * q_ref + cfg.rtpt_quality_memory * q
            if good:
                bad_since = None
            else:
                bad_since = tm if bad_since is None else bad_since
                if tm - bad_since >= cfg.rtpt_lost_seconds:
                    lost_at = bad_since
                    break
            R = r_est
            times.append(tm)
            rots.append(R)
            quality.append(q)
            if good:
                K.update_map(b, R, O, N, kmat, camera.width, camera.height, K.footprint_bbox(R, rays, w, h))
                updates += 1
            if t_prev is not None:
                bar.update(tm - t_prev)
            t_prev = tm
        bar.done()  # the stage has ended: its bar at 100 %
    finally:
        bar.close()
    return _rtpt_result(cfg, chunks, times, rots, quality, lost_at, updates, O, N, wall0, tic, compile_s)
