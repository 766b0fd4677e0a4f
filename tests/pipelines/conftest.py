"""A short simulated sequence shared by the SLAM / back-end tests (simulated once per session)."""
import pytest


@pytest.fixture(scope="session")
def short_sequence(ti_runtime):
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence

    # 1.2 s DAVIS240C (distorted), ~1 M events/s, gyro bias large enough to make dead reckoning drift
    return simulate_sequence(SimulatorConfig(scene="bay", duration=1.2, max_angular_velocity=3.0, seed=3,
                                             gyro_bias_std=0.03))


@pytest.fixture(scope="session")
def short_dataset(short_sequence, tmp_path_factory):
    from ti_cmax.simulate import write_sequence

    out = tmp_path_factory.mktemp("seq") / "short"
    write_sequence(short_sequence, out)
    return out


@pytest.fixture(scope="session")
def engine_dataset(ti_runtime, tmp_path_factory):
    """0.6 s DAVIS240C (about 1 M events) for the runs that compare or check the kernel engines."""
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence, write_sequence

    seq = simulate_sequence(SimulatorConfig(scene="bay", duration=0.6, max_angular_velocity=3.0, seed=3))
    return write_sequence(seq, tmp_path_factory.mktemp("engine") / "seq", events_format="h5")
