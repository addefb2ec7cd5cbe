"""Shared fixtures: small simulated datasets written once per test session, and folders for a
module's own data that go when its tests are done."""
import fcntl
import os
import pickle
import shutil

import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

from so_transients.sim.config import SimConfig  # noqa: E402
from so_transients.sim.simulate import simulate  # noqa: E402


def load_group(dataset, wafer="w16", band="f090"):
    """One wafer-band group of a simulated dataset's first observation, through its Context."""
    from sotodlib import core

    ctx = core.Context(str(dataset.context))
    return ctx.get_obs(dataset.obs_ids[0], dets={"wafer_slot": wafer, "bandpass": band})


def run_steps(aman, steps):
    """Run preprocess ``steps`` (config entries) in process on ``aman``: each step's
    ``process`` then ``calc_and_save``; returns the proc AxisManager."""
    from sotodlib import core
    from sotodlib.preprocess import Pipeline

    proc = core.AxisManager(aman.dets, aman.samps)
    for step in Pipeline(steps):
        step.process(aman, proc)
        step.calc_and_save(aman, proc)
    return proc


def run_sim(path, **sections):
    """Simulate a dataset into ``path`` from config sections given as dicts."""
    config = SimConfig.from_dict({"output": str(path), **sections})
    return simulate(config, progress=False)


#: A 3 Jy flare at 120 s on the path of one w16 f090 detector.
BRIGHT_FLARE = {"at_detector": "w16_f090_p100A", "at_time": 120.0, "t_peak": 120.0,
                "s_peak_mjy": 3000.0, "t_rise": 5.0}


def run_imperfect_sim(path, flare, duration, dead_mode="nan", seed=43):
    """One MF wafer at f090 with ``flare`` (a flares-list entry) and imperfect detectors:
    16 % dead (``dead_mode``: zeros or NaN), 2 % ten times noisier, 200 cosmic-ray glitches
    per hour."""
    return run_sim(path, seed=seed, observation={"duration": duration},
                   instrument={"bands": ["f090"]},
                   detector_yield={"dead_fraction": 0.16, "dead_mode": dead_mode,
                                   "noisy_fraction": 0.02, "noisy_factor": 10.0},
                   glitches={"enabled": True, "rate_per_hour": 200},
                   flares={"list": [flare]})


@pytest.fixture(scope="module")
def module_tmp(tmp_path_factory):
    """``module_tmp(name)``: a new folder for a module-scoped fixture's data, deleted once
    the module's tests are done. The suite simulates and processes over 10 GB in all; kept to
    the end of the session, that fills a small CI disk."""
    made = []

    def mktemp(name):
        made.append(tmp_path_factory.mktemp(name))
        return made[-1]

    yield mktemp
    for path in made:
        shutil.rmtree(path, ignore_errors=True)


def shared_dataset(tmp_path_factory, name, make):
    """``make(folder)``'s result, made once per test session for every xdist worker: the
    first worker to ask makes it in a folder of the session's shared root (under a lock, the
    others wait for it) and pickles it there; the others unpickle it. Its users only read
    it. Without xdist, once per session as any session fixture."""
    base = tmp_path_factory.getbasetemp()
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "shared"
    root.mkdir(exist_ok=True)
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        done = root / f"{name}.pkl"
        if done.exists():
            return pickle.loads(done.read_bytes())
        folder = root / name
        shutil.rmtree(folder, ignore_errors=True)      # a worker that failed half way
        result = make(folder)
        done.write_bytes(pickle.dumps(result))
        return result


@pytest.fixture(scope="session")
def imperfect_bright_dataset(tmp_path_factory):
    """``get(dead_mode)``: :func:`run_imperfect_sim` with ``BRIGHT_FLARE`` over 240 s,
    simulated once per session and dead mode (tests only read it)."""
    def get(dead_mode):
        return shared_dataset(tmp_path_factory, f"imperfect_{dead_mode}",
                              lambda folder: run_imperfect_sim(folder, BRIGHT_FLARE, 240.0,
                                                               dead_mode))

    return get


@pytest.fixture(scope="session")
def noisy_dataset(tmp_path_factory):
    """Five minutes of one MF wafer (both bands) with every noise component on."""
    return shared_dataset(tmp_path_factory, "noisy", lambda folder: run_sim(
        folder, seed=11, observation={"duration": 300.0},
        flares={"n": 2, "s_peak_mjy": [500, 1000]}))


@pytest.fixture(scope="session")
def two_flare_dataset(tmp_path_factory):
    """Five minutes of w16 at f090 (every noise component) with two bright flares; tests
    that run the site pipeline on it write their configs and archives elsewhere
    (``write_site_config(..., path=..., results=...)``)."""
    return shared_dataset(tmp_path_factory, "two_flares", lambda folder: run_sim(
        folder, seed=41, observation={"duration": 300.0}, instrument={"bands": ["f090"]},
        flares={"n": 2, "s_peak_mjy": [1500, 2500], "t_rise": [2, 20]}))


@pytest.fixture(scope="session")
def bright_source_dataset(tmp_path_factory):
    """One MF wafer at f090 with white noise only, a 50 Jy steady source and a bright flare,
    each placed exactly on the path of a chosen detector."""
    return run_sim(tmp_path_factory.mktemp("bright"), seed=2,
                   observation={"duration": 100.0},
                   instrument={"tubes": ["i1"], "wafers": ["w16"], "bands": ["f090"]},
                   atmosphere={"enabled": False}, cmb={"enabled": False},
                   point_sources={"list": [{"at_detector": "w16_f090_p200A", "at_time": 30.0,
                                            "flux_mjy": 50000.0}]},
                   flares={"list": [{"at_detector": "w16_f090_p100A", "at_time": 60.0,
                                     "t_peak": 60.0, "s_peak_mjy": 20000.0, "t_rise": 2.0}]})


def add_socat_asteroid(client, name, mpc_id, points, flux=None):
    """An asteroid with ephemeris points ``[(ctime, ICRS), ...]`` written with socat's own DB
    ``client``, in the API of the socat installed: 0.1 (socat's main: the client's methods,
    times as astropy Times) or 0.0.2 (its sub-clients, ctimes). Returns its sso_id."""
    from astropy.time import Time

    if hasattr(client, "create_sso"):
        sso = client.create_sso(name=name, MPC_id=mpc_id)
        create, when = client.create_ephem, lambda t: Time(t, format="unix")
    else:
        sso = client.sso.create_sso(name=name, MPC_id=mpc_id)
        create, when = client.ephem.create_ephem, lambda t: t
    for t, position in points:
        create(sso_id=sso.sso_id, MPC_id=mpc_id, name=name, time=when(t), position=position,
               flux=flux)
    return sso.sso_id
