"""Monte Carlo ensembles: physics against closed forms, per-trajectory failures, chunking,
sharding across simulated devices and processes, interrupted runs that resume."""

import json
import os
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special
from helpers import INTEGRATION, host_devices_env, tol
from test_cli import run_cli

import jaxdyn as jd

ROOT = Path(__file__).resolve().parent.parent
WORKER = Path(__file__).resolve().parent / "_ensemble_worker.py"
FREE = jd.Scene(jd.RigidBody(inertia=[1.0, 2.0, 2.5]))
Y0 = FREE.state(omega=[0.1, 1.0, 0.1])
VARY = {"omega": jd.Normal([0.1, 1.0, 0.1], 0.05), "inertia[0]": jd.Uniform(0.9, 1.1)}
ROD = jd.Scene(jd.FallingRod(length=1.0))


def _free(**kw):
    kw = {"n": 48, "key": 1, "vary": VARY, "chunk_size": 16, "rtol": 1e-10, "atol": 1e-12,
          **kw}
    return jd.ensemble(FREE, Y0, 5.0, **kw)


def _samples(n, key=1):
    """The samples of `_free`, drawn again through the documented rule."""
    def one(i):
        k = jax.random.fold_in(jax.random.key(key), i)
        from jaxdyn._distributions import name_seed

        w = VARY["omega"].sample(jax.random.fold_in(k, name_seed("omega")), (3,), jnp.float64)
        i0 = VARY["inertia[0]"].sample(jax.random.fold_in(k, name_seed("inertia[0]")), (),
                                       jnp.float64)
        return w, jnp.array([1.0, 2.0, 2.5]).at[0].set(i0)
    return jax.vmap(one)(jnp.arange(n))


@pytest.fixture(scope="module")
def free_adaptive():
    return _free()


def test_final_rates_match_the_closed_form(free_adaptive):
    res = free_adaptive
    assert res.n == res.completed == 48 and res.failed == 0
    w0, inertia = _samples(48)
    exact = jax.vmap(lambda i, w: jd.torque_free_omega(i, w, 5.0))(inertia, w0)
    assert np.allclose(res.values["omega"], exact, rtol=0, atol=100 * tol(INTEGRATION))
    # Conserved quantities of each run, against the sampled initial state.
    energy = 0.5 * jnp.sum(inertia * w0**2, axis=1)
    assert np.allclose(res.values["energy"], energy, rtol=1e-9)
    assert np.allclose(res.values["t_final"], 5.0)


def test_modes_agree(free_adaptive):
    for mode in ("lockstep", "vmap"):
        other = _free(mode=mode)
        assert np.allclose(other.values["omega"], free_adaptive.values["omega"], atol=1e-8)
    lock = _free(mode="lockstep")
    steps = lock.steps.reshape(3, 16)  # one step size for each chunk of 16
    assert np.all(steps == steps[:, :1])


@pytest.mark.optimized  # (bit for bit: the programs a user runs)
def test_samples_do_not_depend_on_the_chunk_size():
    other = _free(chunk_size=48)
    assert np.array_equal(other.values["omega"], _free().values["omega"])


def _started_from(traj):
    return {"omega0": traj.ys["omega"][0], "inertia": traj.scene.parameters()["inertia"]}


def _started(mode, key, spread):
    """21 free bodies in chunks of 8 observed at t0, three names varied."""
    return jd.ensemble(FREE, FREE.state(omega=[1e-3, 1.0, 1e-3]), 1.0, n=21, key=key,
                       chunk_size=8, mode=mode, ts=np.array([0.0, 1.0]), observe=_started_from,
                       vary={"inertia": jd.LogNormal([1.0, 2.0, 2.5], 0.01 * spread),
                             "omega[0]": jd.Normal(0.0, 1e-3 * spread),
                             "omega[2]": jd.Uniform(-1e-3, 1e-3)})


@pytest.mark.parametrize("mode", ["vmap", "adaptive"])
@pytest.mark.optimized  # (bit for bit: the programs a user runs)
def test_the_varied_values_are_the_ones_each_trajectory_started_from(mode, monkeypatch):
    """`varied()` lists, to the last bit, the values each trajectory started from (its state
    saved at t0, its scene's parameters), over chunks with a padded last one: the chunks'
    draws come from a program of their own, which `varied()` runs again."""
    res = _started(mode, key=11, spread=1.0)
    varied = res.varied()
    assert res.completed == 21 and set(varied) == {"inertia", "omega[0]", "omega[2]"}
    assert np.array_equal(res.values["inertia"], varied["inertia"])
    assert np.array_equal(res.values["omega0"][:, 0], varied["omega[0]"])
    assert np.array_equal(res.values["omega0"][:, 2], varied["omega[2]"])
    assert np.all(res.values["omega0"][:, 1] == 1.0)
    assert len(np.unique(varied["omega[0]"])) == 21  # (one draw per trajectory)
    # Another key and spread: new draws from the same programs (their arrays are arguments),
    # nothing compiled or looked up in the compilation cache.
    from jax._src import compiler

    compiled = []
    original = compiler.get_compile_options
    monkeypatch.setattr(compiler, "get_compile_options",
                        lambda *a, **k: compiled.append(1) or original(*a, **k))
    again = _started(mode, key=12, spread=2.0)
    assert compiled == []
    assert np.array_equal(again.values["omega0"][:, 0], again.varied()["omega[0]"])
    assert not np.any(np.isin(again.varied()["omega[0]"], varied["omega[0]"]))


def test_statistics_are_those_of_the_kept_values(free_adaptive):
    res = free_adaptive
    v = res.values["energy"]
    s = res.statistics["energy"]
    assert s["count"] == 48
    assert np.isclose(s["mean"], v.mean(), rtol=1e-13)
    assert np.isclose(s["std"], v.std(ddof=1), rtol=1e-10)
    assert s["min"] == v.min() and s["max"] == v.max()
    assert np.isclose(s["quantiles"]["50%"], np.median(v))
    # Statistics only: nothing is kept per trajectory, the same moments.
    lean = _free(keep=False)
    assert lean.values == {}
    assert np.isclose(lean.statistics["energy"]["std"], s["std"], rtol=1e-12)


def test_rod_fall_times_match_quadrature():
    res = jd.ensemble(ROD, ROD.state(theta=0.01), 5.0, n=24, key=2, chunk_size=16,
                      vary={"theta": jd.Uniform(0.005, 0.3), "theta_dot": jd.Normal(0.0, 0.05)})
    assert res.completed == 24
    assert res.status_counts() == {"event": 24}
    theta = res.values["theta"]
    assert np.allclose(np.abs(theta), np.pi / 2, atol=1e-12)  # every rod lies flat (event to ulps)
    # Independent route: the initial values are recovered from the energy integral.
    rod = ROD.body
    lo = jax.vmap(lambda i: jax.random.fold_in(jax.random.key(2), i))(jnp.arange(24))
    from jaxdyn._distributions import name_seed

    th0 = jax.vmap(lambda k: jd.Uniform(0.005, 0.3).sample(
        jax.random.fold_in(k, name_seed("theta")), (), jnp.float64))(lo)
    rate0 = jax.vmap(lambda k: jd.Normal(0.0, 0.05).sample(
        jax.random.fold_in(k, name_seed("theta_dot")), (), jnp.float64))(lo)
    fall = np.array([float(rod.fall_time(a, b)) for a, b in zip(th0, rate0)])
    assert np.allclose(res.values["t_final"], fall, rtol=1e-7)


# -- the flip of a spin about the intermediate axis, nutation cones, rod fall times ------------

FLIP_BODY = jd.Scene(jd.RigidBody(inertia=[1.0, 2.0, 2.7]))  # 10 % inside the triangle inequality
FLIP_TS = jnp.linspace(0.0, 80.0, 801)
FLIP_SIGMA = 1e-3  # transverse rate spread (rad/s), about a spin of 1 rad/s


def _flip_times(traj):
    # The first two sign changes of omega_2, linearly interpolated between saved samples.
    t, w2 = traj.ts, traj.ys["omega"][:, 1]
    change = traj.valid[:-1] & traj.valid[1:] & (jnp.sign(w2[:-1]) != jnp.sign(w2[1:]))
    t_cross = jnp.where(change, t[:-1] + w2[:-1] / (w2[:-1] - w2[1:]) * (t[1:] - t[:-1]),
                        jnp.inf)
    first = jnp.min(t_cross)
    second = jnp.min(jnp.where(t_cross > first, t_cross, jnp.inf))
    return {"flip_1": first, "flip_2": second, "omega0": traj.ys["omega"][0],
            "inertia": traj.scene.parameters()["inertia"]}


def _flip_ensemble(n, key, inertia_spread):
    return jd.ensemble(
        FLIP_BODY, FLIP_BODY.state(omega=[0.0, 1.0, 0.0]), 80.0, n=n, key=key, ts=FLIP_TS,
        vary={"inertia": jd.LogNormal([1.0, 2.0, 2.7], inertia_spread),
              "omega[0]": jd.Normal(0.0, FLIP_SIGMA), "omega[2]": jd.Normal(0.0, FLIP_SIGMA)},
        observe=_flip_times)


def _flip_constants(inertia, w2):
    """About a spin w2 about the intermediate axis: the growth rate lam of the linearisation,
    the ratio kappa = -omega_3 / omega_1 along its growing mode, and the amplitude A of omega_1
    on the separatrix."""
    i1, i2, i3 = np.asarray(inertia).T
    lam = np.abs(w2) * np.sqrt((i2 - i1) * (i3 - i2) / (i1 * i3))
    kappa = np.sqrt((i2 - i1) * i1 / ((i3 - i2) * i3))
    amp = np.abs(w2) * np.sqrt(i2 * (i3 - i2) / (i1 * (i3 - i1)))
    return lam, kappa, amp


def _matched_flip_time(inertia, omega0):
    """Time of the first flip: the growing mode a e^(lam t) of the linearisation, with
    a = (omega_1 - omega_3 / kappa) / 2, matched to the separatrix's tail 2 A e^(lam (t - t_f))."""
    lam, kappa, amp = _flip_constants(inertia, omega0[:, 1])
    a = (omega0[:, 0] - omega0[:, 2] / kappa) / 2
    return np.log(2 * amp / np.abs(a)) / lam


@pytest.mark.parametrize("inertia_spread", [0.0, 0.01])
def test_flip_times_match_the_period_and_the_matched_asymptotics(inertia_spread):
    # Each run: the time between the first two flips is half the closed-form period 4 K(m) / lam'
    # of its own inertia and rates, and the first flip comes at t_f = ln(2 A / |a|) / lam.
    res = _flip_ensemble(400, 1, inertia_spread)
    assert res.failed == 0 and np.all(np.isfinite(res.values["flip_2"]))
    v = res.values
    half = np.asarray(jax.vmap(jd.torque_free_period)(v["inertia"], v["omega0"])) / 2
    assert np.max(np.abs(v["flip_2"] - v["flip_1"] - half)) < 1e-3
    assert np.max(np.abs(v["flip_1"] - _matched_flip_time(v["inertia"], v["omega0"]))) < 1e-3


def test_flip_times_follow_their_law():
    # With the nominal inertia, t_f depends only on |a|, a Gaussian of standard deviation
    # sigma_a = sigma sqrt(1 + kappa^-2) / 2, so P(t_f > tau) = erf(u) with
    # u = 2 A e^(-lam tau) / (sqrt(2) sigma_a): a Kolmogorov-Smirnov test at the 95 % level.
    res = _flip_ensemble(1000, 2, 0.0)
    lam, kappa, amp = _flip_constants([1.0, 2.0, 2.7], 1.0)
    sigma_a = 0.5 * FLIP_SIGMA * np.sqrt(1 + kappa**-2)
    t = np.sort(res.values["flip_1"])
    cdf = scipy.special.erfc(2 * amp * np.exp(-lam * t) / (np.sqrt(2) * sigma_a))
    steps = np.arange(t.size + 1) / t.size  # the empirical distribution below and above each t
    ks = np.max(np.maximum(steps[1:] - cdf, cdf - steps[:-1]))
    assert ks < 1.36 / np.sqrt(t.size), ks


def test_plate_bodies_outside_the_triangle_inequality_are_marked_invalid():
    # I = (1, 2, 3) is a flat plate, I_3 = I_1 + I_2: with a 1 % spread per moment about half the
    # draws are impossible bodies. Exactly those runs are marked invalid_input; the rest run.
    scene = jd.Scene(jd.RigidBody(inertia=[1.0, 2.0, 3.0]))
    res = jd.ensemble(scene, scene.state(omega=[0.0, 1.0, 0.0]), 1.0, n=400, key=0,
                      vary={"inertia": jd.LogNormal([1.0, 2.0, 3.0], 0.01)},
                      observe=lambda traj: {"inertia": traj.scene.parameters()["inertia"]})
    moments = np.sort(res.values["inertia"], axis=1)
    impossible = moments[:, 2] > moments[:, 0] + moments[:, 1]
    assert np.array_equal(res.status == 5, impossible) and np.array_equal(res.ok, ~impossible)
    assert abs(res.failed / res.n - 0.5) < 3 * np.sqrt(0.25 / res.n)


def _cone_closed_form(inertia, omega0, k):
    """Largest angle between body axis k and H on the polhode, from the energy and momentum
    integrals: furthest from axis 3 where h_1 = 0, from axis 1 where h_3 = 0."""
    i1, i2, i3 = inertia.T
    hh = np.sum((inertia * omega0) ** 2, axis=-1)
    two_t = np.sum(inertia * omega0**2, axis=-1)
    if k == 2:
        s2 = (two_t - hh / i3) / (hh * (1 / i2 - 1 / i3))
    elif k == 0:
        s2 = (hh / i1 - two_t) / (hh * (1 / i1 - 1 / i2))
    else:
        s2 = np.ones_like(hh)  # through the separatrix: 90 degrees from H
    return np.arcsin(np.sqrt(np.clip(s2, 0.0, 1.0)))


def _cone_angles(traj):
    h = traj.angular_momentum
    h2 = jnp.sum(h**2, axis=-1, keepdims=True)
    angle = jnp.arctan2(jnp.sqrt(jnp.maximum(h2 - h**2, 0.0)), jnp.abs(h))
    return {"max_angle": jnp.max(jnp.where(traj.valid[:, None], angle, 0.0), axis=0),
            "omega0": traj.ys["omega"][0], "inertia": traj.scene.parameters()["inertia"]}


@pytest.mark.parametrize("k, rel", [(0, 2e-3), (1, 2e-2), (2, 2e-3)])
def test_nutation_cones_match_the_polhode(k, rel):
    # Spins about each axis with 2 % transverse rate errors and a 1 % inertia spread: the largest
    # sampled angle between the spin axis and H lies just below the closed form (samples 0.05 s
    # apart against nutation periods of 8 to 11 s; about the intermediate axis the angle peaks in
    # a cusp, which the samples can miss by a degree).
    unit = np.eye(3)[k]
    res = jd.ensemble(FLIP_BODY, FLIP_BODY.state(omega=unit), 40.0, n=200, key=10 + k,
                      ts=jnp.linspace(0.0, 40.0, 801),
                      vary={"inertia": jd.LogNormal([1.0, 2.0, 2.7], 0.01),
                            "omega": jd.Normal(unit, 0.02 * (1 - unit))},
                      observe=_cone_angles)
    assert res.failed == 0
    v = res.values
    closed = _cone_closed_form(v["inertia"], v["omega0"], k)
    below = (closed - v["max_angle"][:, k]) / closed
    assert np.all(below > -1e-9) and np.all(below < rel), (below.min(), below.max())


def test_rod_fall_times_from_nearly_upright():
    # theta0 log-normal about 1e-3 rad, a small random initial rate: some rods fall backward.
    # Every run ends flat, at the quadrature's fall time for its own start, and the median fall
    # time is that of the median angle (the initial rate hardly matters at the median).
    rod = jd.FallingRod(length=1.0, mass=1.0, g=9.81)
    scene = jd.Scene(rod)

    def fall(traj):
        return {**jd.final_state(traj), "theta0": traj.ys["theta"][0],
                "theta_dot0": traj.ys["theta_dot"][0]}

    res = jd.ensemble(scene, scene.state(theta=1e-3), 5.0, n=3000, key=20, observe=fall,
                      vary={"theta": jd.LogNormal(1e-3, 1.0), "theta_dot": jd.Normal(0.0, 1e-3)})
    v = res.values
    assert np.all(v["event.flat"]) and np.any(v["theta"] < 0)
    t_quad = np.asarray(jax.jit(jax.vmap(rod.fall_time))(v["theta0"], v["theta_dot0"]))
    assert np.max(np.abs(v["t_final"] / t_quad - 1)) < 1e-6
    median = res.statistics["t_final"]["quantiles"]["50%"]
    assert abs(median / float(rod.fall_time(1e-3)) - 1) < 0.01


@pytest.mark.parametrize("mode", ["adaptive", "vmap"])
def test_saved_times_and_a_custom_observation(mode):
    ts = jnp.linspace(0.0, 5.0, 11)

    def observe(traj):
        w2 = traj.ys["omega"][:, 1]
        return {"min_w2": jnp.min(jnp.where(traj.valid, w2, jnp.inf)), "w2_at_ts": w2}

    res = _free(n=8, ts=ts, observe=observe, mode=mode)
    w0, inertia = _samples(8)
    exact = jax.vmap(lambda i, w: jd.torque_free_omega(i, w, ts))(inertia, w0)
    assert np.allclose(res.values["w2_at_ts"], exact[..., 1], atol=1e-8)
    assert np.allclose(res.values["min_w2"], exact[..., 1].min(axis=1), atol=1e-8)


def test_every_mode_with_saved_times_is_a_cacheable_program(caplog):
    """Each mode's chunk program with saved times is written to the persistent compilation
    cache: none holds a host callback (diffrax's `SaveAt(ts)` check of traced times would)."""
    compiled = []

    def listen(event, **kw):  # a compilation that went through the persistent cache
        if event == "/jax/compilation_cache/compile_requests_use_cache":
            compiled.append(event)

    jax.monitoring.register_event_listener(listen)
    try:
        for mode in ("adaptive", "lockstep", "vmap"):
            compiled.clear()
            with caplog.at_level("DEBUG", logger="jax"):
                caplog.clear()
                _free(n=4, chunk_size=4, ts=jnp.linspace(0.0, 5.0, 17), mode=mode)
            assert compiled, mode  # a program of its own was built (else the test sees none)
            assert "host callback" not in caplog.text, mode
    finally:
        jax.monitoring.unregister_event_listener(listen)


def test_a_failing_trajectory_does_not_stop_the_batch():
    # Inertia samples that break the triangle inequality, and a tiny step budget for fast spins.
    res = jd.ensemble(FREE, Y0, 5.0, n=40, key=0, chunk_size=16,
                      vary={"inertia[2]": jd.Uniform(2.5, 3.5)})
    counts = res.status_counts()
    assert counts["invalid_input"] == int(np.sum(res.status == 5)) > 0
    assert counts["completed"] + counts["invalid_input"] == 40
    (first,) = res.failures(1)
    assert "triangle inequality" in first["message"]
    short = _free(n=16, max_steps=25, rtol=1e-6, atol=1e-8,
                  vary={"omega[1]": jd.Uniform(0.01, 8.0)})
    assert set(short.status_counts()) == {"completed", "max_steps_reached"}
    assert short.failures(1)[0]["status"] == "max_steps_reached"
    report = short.report()
    assert report["failed"] == short.failed > 0
    json.dumps(report)


def test_bad_input_is_named():
    with pytest.raises(jd.ParameterError, match="unknown name 'spin'"):
        _free(vary={"spin": jd.Normal(0.0, 1.0)})
    with pytest.raises(jd.ParameterError, match="mode='fast'"):
        _free(mode="fast")
    with pytest.raises(jd.ParameterError, match="does not fit"):
        _free(vary={"omega": jd.Normal([0.0, 1.0], 1.0)})
    with pytest.raises(jd.ParameterError, match="std"):
        jd.Normal(0.0, -1.0)
    with pytest.raises(jd.ParameterError, match="explicit Runge-Kutta"):
        import diffrax as dfx

        _free(solver=dfx.Kvaerno5())


def test_distribution_syntax():
    assert jd.parse_distribution("normal(1, 0.5)") == jd.Normal(1.0, 0.5)
    u = jd.parse_distribution("uniform([0, 1], [1, 2])")
    assert np.array_equal(u.low, [0.0, 1.0])
    assert np.isclose(float(jd.parse_distribution("2.5").value), 2.5)
    for bad in ("gauss(0, 1)", "normal(0)", "normal(a, b)", "uniform(1, 0)"):
        with pytest.raises(jd.ParameterError):
            jd.parse_distribution(bad)
    # Shifted and scaled: the distribution of c + X and c X, checked by sampling.
    d = jd.LogNormal(1.0, 0.1).scaled(3.0)
    x = d.sample(jax.random.key(0), (20000,), jnp.float64)
    assert abs(float(jnp.median(x)) - 3.0) < 0.02
    assert abs(float(jnp.std(jnp.log(x))) - 0.1) < 0.005


def _worker(*args, env=None):
    out = subprocess.run([sys.executable, str(WORKER), *args], capture_output=True,
                         text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("mode, chunk", [("adaptive", "32"), ("adaptive", "128"),
                                         ("lockstep", "32")])
def test_sharded_across_devices_equals_one_device(mode, chunk):
    """100 trajectories on 4 devices against one device. Adaptive steps in chunks of 32 (four
    chunks): one program per device, each device going on to its next chunk; in one chunk of
    100: one program over the four devices (compiled once). Lock-step: one program over the
    devices, whose step sizes are reduced across them."""
    env = host_devices_env(4)
    sharded, single = _worker(mode, "--chunk", chunk, "--then-devices", "1", env=env)
    assert sharded["local_devices"] == 4 and sharded["devices"] == 4 and single["devices"] == 1
    assert sharded["programs"] == (["per_device"] if chunk == "32" and mode == "adaptive"
                                   else ["one"])
    assert sharded["status"] == single["status"]
    assert sharded["steps"] == single["steps"]
    np.testing.assert_allclose(sharded["omega"], single["omega"], rtol=1e-14, atol=1e-15)


def test_processes_joined_by_jax_distributed_share_a_run(tmp_path):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = str(s.getsockname()[1])
    procs = [subprocess.Popen([sys.executable, str(WORKER), "adaptive", "--out",
                               str(tmp_path / "shared"), "--process", str(i), "--processes",
                               "2", "--port", port], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for i in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    for p, (_, err) in zip(procs, outs):
        assert p.returncode == 0, err[-3000:]
    results = [json.loads(o.strip().splitlines()[-1]) for o, _ in outs]
    alone = _worker("adaptive")
    for r in results:
        assert r["process_count"] == 2
        assert r["omega"] == alone["omega"] and r["status"] == alone["status"]
    assert len(list((tmp_path / "shared").glob("chunk-*.npz"))) == 4  # 100 in chunks of 32


def _cli(*args):
    return [sys.executable, "-m", "jaxdyn", "montecarlo", "falling-rod", "--n", "2000",
            "--chunk", "64", "--vary", "theta=uniform(0.001, 0.2)", "--json", *args]


def test_an_interrupted_run_resumes_to_the_same_result(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.Popen(_cli("--out", str(out), "--mode", "vmap"), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    deadline = time.monotonic() + 240
    while not list(out.glob("chunk-*.npz")) and proc.poll() is None:
        assert time.monotonic() < deadline, "no chunk written"
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)  # as a crash would
    proc.wait()
    written = len(list(out.glob("chunk-*.npz")))
    assert 1 <= written < 32  # 2000 trajectories in chunks of 64
    resumed = json.loads(subprocess.run(_cli("--out", str(out), "--mode", "vmap"),
                                        capture_output=True, text=True, check=True).stdout)
    whole = json.loads(subprocess.run(_cli("--mode", "vmap"), capture_output=True, text=True,
                                      check=True).stdout)
    assert resumed["resumed_chunks"] == written
    assert resumed["statistics"] == whole["statistics"]
    assert resumed["completed"] == whole["completed"] == 2000


def test_corrupt_and_foreign_chunk_files_are_detected(tmp_path):
    out = tmp_path / "run"
    first = _free(n=40, out=out)
    path = out / "chunk-000001.npz"
    path.write_bytes(path.read_bytes()[:100])  # truncated, as a full disk might leave it
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        again = _free(n=40, out=out)
    assert any("unreadable" in str(w.message) for w in caught)
    assert again.recomputed_chunks == (1,) and again.resumed_chunks == 2
    assert np.array_equal(again.values["omega"], first.values["omega"])
    # A file from another chunk (or run) fails its checks.
    (out / "chunk-000002.npz").write_bytes((out / "chunk-000000.npz").read_bytes())
    with pytest.warns(UserWarning, match="another run"):
        third = _free(n=40, out=out)
    assert np.array_equal(third.values["omega"], first.values["omega"])
    with pytest.raises(jd.ParameterError, match="different run"):
        _free(n=40, out=out, rtol=1e-9)


def test_montecarlo_command(tmp_path, capsys):
    proc = subprocess.run(_cli(), capture_output=True, text=True, check=True)
    out = json.loads(proc.stdout)
    assert out["n"] == 2000 and out["completed"] == 2000 and out["failed"] == 0
    assert out["devices"] == (os.cpu_count() or 1)  # one JAX CPU device per core by default
    t = out["statistics"]["t_final"]
    rod = jd.FallingRod()
    # Fall times between those of the extreme angles of the uniform draw.
    assert rod.fall_time(0.2) < t["min"] < t["max"] < rod.fall_time(0.001)
    # Bad input: exit status 2 and one line (in this process, as test_cli.py runs the command;
    # `test_console_script_fails_cleanly_without_traceback` checks a process's stderr).
    status, out, err = run_cli(capsys, *_cli("--vary", "theta_dot=gauss(0, 1)")[3:])
    assert status == 2 and out == ""
    assert err.count("\n") == 1 and "gauss" in err and "Traceback" not in err
    status, out, err = run_cli(capsys, *_cli("--devices", "0")[3:])
    assert status == 2 and out == "" and err.count("\n") == 1 and "--devices=0" in err


@pytest.mark.optimized  # (bit for bit: the programs a user runs)
def test_compacting_the_batch_changes_no_trajectory():
    """Per-trajectory stepping moves the running trajectories to smaller batches as others
    finish: states, saved values, event times, statuses and step counts stay bit for bit."""
    import diffrax as dfx

    from jaxdyn._batch_solve import batch_solve

    def field(p, t, y):  # a pendulum-like rod, stopped when it lies flat
        s = jnp.sin(y["theta"])
        return {"theta": y["rate"], "rate": p["k"] * s / (1 + 3 * s**2)}

    def conditions(p, t, y):
        return jnp.stack([jnp.pi / 2 - jnp.abs(y["theta"])])

    n = 40
    rng = np.random.default_rng(5)
    y0 = {"theta": jnp.asarray(rng.uniform(0.01, 0.3, n)), "rate": jnp.zeros(n)}
    params = {"k": jnp.asarray(rng.uniform(5.0, 40.0, n))}
    flags = jnp.zeros((n, 1), bool).at[3, 0].set(True)  # one invalid input
    ts = jnp.linspace(0.0, 1.5, 7)

    def run(compact):
        return jax.jit(lambda y0, params: batch_solve(
            field, conditions, ("flat",), flags, params, y0, 0.0, 3.0, ts,
            solver=dfx.Tsit5(), rtol=1e-9, atol=1e-11, max_steps=60, lockstep=False,
            compact_rows=compact))(y0, params)

    whole, compacted = run(None), run(4)
    assert set(np.asarray(whole.status).tolist()) >= {1, 2, 5}  # events, max_steps, invalid
    for a, b in zip(jax.tree.leaves(whole), jax.tree.leaves(compacted)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_a_second_call_of_the_same_structure_traces_nothing():
    # After the first call, an ensemble of the same scene structure with other values (other
    # moments, other rates, a parameter of one run out of its range) traces and compiles
    # nothing: the checks' messages come from the first call's trace (per structure), and
    # they are the ones for these values.
    traces = []

    def listener(name, *args, **kwargs):
        if name in ("/jax/core/compile/jaxpr_trace_duration",
                    "/jax/core/compile/jaxpr_to_mlir_module_duration"):
            traces.append(name)

    def run(inertia, omega):
        scene = jd.Scene(jd.RigidBody(inertia=inertia))
        return jd.ensemble(scene, scene.state(omega=omega), 2.0,
                           parameters={"inertia": np.array([inertia, [-1.0, 2.0, 2.5],
                                                            [1.1, 2.0, 2.5]])})

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        jax.jit(lambda x: 2 * x).lower(1.0)  # (positive control: the listener sees a trace)
        assert traces
        first = run([1.0, 2.0, 2.5], [0.1, 1.0, 0.1])
        # (The listener hears every thread: programs the first call left preparing on the
        # other core are finished before the second call is counted.)
        for thread in threading.enumerate():
            if thread.name == "jaxdyn-prepare":
                thread.join()
        traces.clear()
        again = run([3.0, 4.0, 5.0], [0.3, -0.2, 0.4])
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert traces == []
    for res in (first, again):
        assert list(res.ok) == [True, False, True]
        failure, = res.failures()
        assert failure["index"] == 1 and failure["status"] == "invalid_input"
        assert failure["message"].startswith("invalid inertia: principal moments"), failure
    scene = jd.Scene(jd.RigidBody(inertia=[3.0, 4.0, 5.0]))
    single = jd.simulate(scene, scene.state(omega=[0.3, -0.2, 0.4]), 2.0)
    np.testing.assert_allclose(again.values["omega"][0], single.y_final["omega"], rtol=1e-9)


@pytest.mark.parametrize("seed", [0, 7, 2**31 - 1, 2**32 + 5, 2**62 + 3, -1, -(2**40), -(2**63)])
def test_an_integer_key_is_jaxs_key_of_that_seed(seed):
    """An integer `key=` is made on the host (no program compiled for it): the same key as
    `jax.random.key(seed)`, data and draws, for seeds past 32 bits and negative ones; and an
    ensemble given the seed draws what it draws given JAX's key."""
    from jaxdyn._validation import key_from_seed

    ours, jaxs = key_from_seed(seed), jax.random.key(seed)
    assert ours.dtype == jaxs.dtype and ours.shape == jaxs.shape == ()
    np.testing.assert_array_equal(jax.random.key_data(ours), jax.random.key_data(jaxs))
    np.testing.assert_array_equal(jax.random.normal(ours, (4,)), jax.random.normal(jaxs, (4,)))
    if seed == 2**32 + 5:  # (one ensemble: the seed reaches the draws through `ensemble`)
        kw = dict(n=8, vary={"omega[0]": jd.Normal(0.0, 1e-3)})
        a = jd.ensemble(FREE, Y0, 1.0, key=seed, **kw)
        b = jd.ensemble(FREE, Y0, 1.0, key=jaxs, **kw)
        assert a.values.keys() == b.values.keys()
        for name in a.values:
            np.testing.assert_array_equal(np.asarray(a.values[name]), np.asarray(b.values[name]))
        assert not np.all(np.asarray(a.values["omega"])[:, 0] == 0.0)  # (the draws vary)
