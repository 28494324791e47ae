"""Programs kept on disk between processes (`jaxdyn._programs`): a later process reads the
program instead of tracing it, gets the same numbers, and nothing is stored that could be
stale (a structure naming code outside jaxdyn and its libraries)."""

import re
import subprocess
import sys
import uuid

import jax
import numpy as np
import pytest
from helpers import host_devices_env, new_programs

import jaxdyn as jd
from jaxdyn import _programs, _simulate, _solution
from jaxdyn._simulate import simulate_unchecked

SCENE = jd.Scene(jd.FallingRod(length=1.3, mass=2.0, g=9.81))


def _program(calls, options=()):
    """The falling rod's simulation as a stored program; `calls` counts its tracings."""
    leaves, treedef = jax.tree_util.tree_flatten(SCENE)

    def simulate_program(leaves, y0, t1):
        calls.append(1)
        scene = jax.tree_util.tree_unflatten(treedef, leaves)
        traj = simulate_unchecked(scene, y0, t1)
        return traj.t_final, traj.y_final, traj.event, traj.result

    return _programs.StoredProgram("test-simulate", treedef, options, simulate_program), leaves


@pytest.fixture
def stored(tmp_path, monkeypatch):
    monkeypatch.setattr(_programs, "_directory", lambda: tmp_path)
    # A version of its own: each program is compiled afresh, never read from JAX's
    # persistent cache (whose executables are not stored: see
    # test_a_program_held_by_the_compilation_cache_is_not_stored_compiled).
    _programs._version()
    monkeypatch.setattr(_programs, "_VERSION", uuid.uuid4().hex)
    monkeypatch.setattr(_programs, "_QUEUE", [])  # (none prepared by an earlier test)
    return tmp_path


def test_a_later_process_reads_the_program_instead_of_tracing_it(stored):
    y0 = SCENE.state(theta=0.2)
    calls = []
    first, leaves = _program(calls)
    out = first(leaves, y0, np.asarray(5.0))
    assert calls == [1] and len(list(stored.glob("*.exe"))) == 1
    # A new program object for the same structure (as in a new process): read, not traced.
    again, _ = _program(calls)
    out2 = again(leaves, y0, np.asarray(5.0))
    assert calls == [1]
    assert jax.tree.structure(out2) == jax.tree.structure(out)
    for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(out2)):
        np.testing.assert_array_equal(a, b)
    # Independent route: the fall time from the energy integral.
    fall = float(SCENE.body.fall_time(0.2, 0.0))
    assert abs(float(out2[0]) - fall) < 1e-7 * fall and bool(out2[2]["flat"])
    # Other inputs of the same shapes reuse it; other static options are another program.
    out3 = again(leaves, SCENE.state(theta=0.4), np.asarray(5.0))
    assert calls == [1] and float(out3[0]) < float(out[0])
    other, _ = _program(calls, options=("another",))
    other(leaves, y0, np.asarray(5.0))
    # (Here the same program under another key: a program that jaxdyn stores is not also
    # written to JAX's persistent cache, so it is compiled afresh and stored under its key.)
    assert calls == [1, 1] and len(list(stored.glob("*.exe"))) == 2


def test_structures_naming_outside_code_are_never_stored(stored):
    assert _programs._trusted(str(jax.tree_util.tree_structure(SCENE)))
    assert not _programs._trusted("PyTreeDef(CustomNode(MyBody[(<class '__main__.Law'>,)]))")
    assert not _programs._trusted("PyTreeDef(CustomNode(Torque[(<function f at 0x7f00>,)]))")
    calls = []
    program, leaves = _program(calls)
    program.trusted = False  # as for such a structure
    program(leaves, SCENE.state(theta=0.2), np.asarray(5.0))
    assert calls == [1] and not list(stored.iterdir())


def test_without_the_compilation_cache_nothing_is_written(monkeypatch, tmp_path):
    monkeypatch.setattr(_programs, "_directory", lambda: None)
    calls = []
    program, leaves = _program(calls)
    program(leaves, SCENE.state(theta=0.2), np.asarray(5.0))
    assert calls == [1] and not list(tmp_path.iterdir())


def test_weak_types_survive_the_disk(stored):
    """A weakly typed output (a Python scalar in the program, as diffrax's interpolation's
    direction) comes back weakly typed, so that strict promotion accepts it as before."""
    def program(x):
        return {"x": 2 * x, "sign": jax.numpy.where(x[0] > 0, 1, -1)}

    for _ in range(2):  # compiled and stored, then read
        out = _programs.StoredProgram("test-weak", "weak", (), program)(np.ones(3))
        assert jax.typeof(out["sign"]).weak_type and not jax.typeof(out["x"]).weak_type
    assert len(list(stored.glob("*.exe"))) == 1
    with jax.numpy_dtype_promotion("strict"):
        assert float(out["sign"] * np.float64(2.5)) == 2.5


@pytest.mark.parametrize("on_disk", [True, False])
def test_host_and_device_inputs_share_one_compiled_program(on_disk, tmp_path, monkeypatch,
                                                           caplog):
    """A call from host values and the next from the previous call's device arrays (a fit's
    stages, `jd.simulate` from `traj.y_final`) run one compiled program: plain `jax.jit`
    compiled it twice (inputs committed to a device are another lowering)."""
    monkeypatch.setattr(_programs, "_directory", lambda: tmp_path if on_disk else None)
    monkeypatch.setattr(_simulate, "_STRUCTURES", {})  # (this process's programs: none)
    monkeypatch.setattr(_simulate, "_LAST", [_simulate._NO_SCENE])
    monkeypatch.setattr(_solution, "_PROGRAMS", {})
    ts = np.linspace(0.0, 0.1, 37)  # (a signature no other test compiles)
    with jax.log_compiles(), caplog.at_level("WARNING"):
        first = jd.simulate(SCENE, SCENE.state(theta=0.2), 0.1, ts=ts)
        assert first.y_final["theta"].committed  # (the next call's inputs: device arrays)
        second = jd.simulate(SCENE, first.y_final, 0.2, t0=0.1, ts=ts + 0.1)
    compiled = [r.getMessage() for r in caplog.records
                if r.getMessage().startswith("Finished XLA compilation of jit(simulate")]
    assert len(compiled) == 1, compiled
    # The second run continues the first: the same as one run over both spans.
    whole = jd.simulate(SCENE, SCENE.state(theta=0.2), 0.2)
    assert str(second.outcome) == str(whole.outcome)
    np.testing.assert_allclose(float(second.y_final["theta"]), float(whole.y_final["theta"]),
                               rtol=1e-6)


def _load_events():
    """Counts jaxdyn's event for a stored compiled program loaded (`_programs`)."""
    seen = []

    def listen(event, duration, **kwargs):
        if event == "/jaxdyn/programs/load_duration":
            seen.append(duration)

    return seen, listen


def test_a_later_process_loads_this_machines_compiled_program(stored, monkeypatch):
    """The compiled program is stored per machine: a later process loads it (no tracing, no
    lowering, no compilation), another machine's is not used, and a stored program that does
    not run here gives way to the program compiled afresh (and is removed)."""
    y0 = SCENE.state(theta=0.2)
    calls = []
    first, leaves = _program(calls)
    out = first(leaves, y0, np.asarray(5.0))
    assert len(list(stored.glob("*.exe"))) == 1
    seen, listen = _load_events()
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        with jax.log_compiles(False):
            again, _ = _program(calls)
            out2 = again(leaves, y0, np.asarray(5.0))
        assert calls == [1] and len(seen) == 1
        for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(out2)):
            np.testing.assert_array_equal(a, b)
        # Another machine (another processor) sharing the folder does not load it: it traces
        # and compiles the program, and stores its own.
        here = _programs._machine()
        monkeypatch.setattr(_programs, "_MACHINE", "another processor")
        other, _ = _program(calls)
        out_other = other(leaves, y0, np.asarray(5.0))
        assert calls == [1, 1] and len(seen) == 1 and len(list(stored.glob("*.exe"))) == 2
        np.testing.assert_array_equal(out_other[0], out[0])

        # A stored program that fails to run here (a kernel missing from it, as XLA:CPU
        # reports it): the program compiled afresh runs instead, and the stored one is
        # removed.
        def broken(path):
            def run(*args):
                raise jax.errors.JaxRuntimeError("NOT_FOUND: Function fusion not found")
            return run, jax.tree.structure(out)

        monkeypatch.setattr(_programs, "_MACHINE", here)
        monkeypatch.setattr(_programs, "_read_executable", broken)
        third, _ = _program(calls)
        out3 = third(leaves, y0, np.asarray(5.0))
        for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(out3)):
            np.testing.assert_array_equal(a, b)
        # (What remains is the other machine's.)
        assert calls == [1, 1, 1] and len(list(stored.glob("*.exe"))) == 1
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)


def test_a_program_stored_under_other_compile_settings_is_not_read(stored):
    """JAX's settings that change what XLA compiles (here `jax_disable_most_optimizations`,
    which the tests use) are part of a stored program's key, as they are of JAX's own cache
    key: a program compiled with XLA's optimisations off is not read where they are on, nor
    the reverse; each is read again under its own setting."""
    y0 = SCENE.state(theta=0.2)
    calls = []
    before = jax.config.values["jax_disable_most_optimizations"]
    try:
        outs = []
        for less in (True, False, True, False):
            jax.config.update("jax_disable_most_optimizations", less)
            program, leaves = _program(calls)  # (a new object: as in a later process)
            outs.append(program(leaves, y0, np.asarray(5.0)))
        assert calls == [1, 1] and len(list(stored.glob("*.exe"))) == 2
    finally:
        jax.config.update("jax_disable_most_optimizations", before)
    # Independent route: the fall time from the energy integral, under either setting.
    fall = float(SCENE.body.fall_time(0.2, 0.0))
    for out in outs:
        assert abs(float(out[0]) - fall) < 1e-7 * fall


def test_clearing_forgets_loaded_programs_and_the_calls_remembered(stored):
    """`_programs.clear_loaded()` is to stored programs what `jax.clear_caches()` is to
    `jax.jit`: this process's compiled programs and the calls that `simulate` and the
    derived outputs remember are dropped; the next call reads the program again (no
    tracing) and gives the same numbers."""
    y0 = SCENE.state(theta=0.2)
    calls = []
    program, leaves = _program(calls)
    out = program(leaves, y0, np.asarray(5.0))
    traj = jd.simulate(SCENE, y0, 1.0)
    energy = traj.energy
    assert program.calls and _simulate._LAST[0][0] is SCENE
    _programs.clear_loaded()
    assert not program.calls and _simulate._LAST[0][0] is None and not _simulate._STRUCTURES
    assert _solution._LAST_OUTPUTS[0][0] is None
    out2 = program(leaves, y0, np.asarray(5.0))
    assert calls == [1]
    for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(out2)):
        np.testing.assert_array_equal(a, b)
    again = jd.simulate(SCENE, y0, 1.0)
    np.testing.assert_array_equal(again.ys["theta"], traj.ys["theta"])
    np.testing.assert_array_equal(again.energy, energy)


def test_a_program_held_by_the_compilation_cache_is_not_stored_compiled(stored, monkeypatch):
    """XLA:CPU's executable read from JAX's persistent cache serialises without its kernels:
    it is never stored (a fresh compilation is)."""
    def program(x):
        return {"y": jax.numpy.cos(x) * 3.0}

    # Compiled where it cannot be stored (as a program calling custom kernels other than
    # LAPACK's): JAX's persistent cache holds it then (a program that jaxdyn stores is not
    # written there).
    with monkeypatch.context() as m:
        m.setattr(_programs, "_storable", lambda lowered, tree, path: None)
        out = _programs.StoredProgram("test-hit", "hit", (), program)(np.ones(5))
    assert not list(stored.glob("*.exe"))
    # The same program where it could be stored: read from JAX's cache, so not stored.
    out2 = _programs.StoredProgram("test-hit", "hit", (), program)(np.ones(5))
    np.testing.assert_array_equal(out["y"], out2["y"])
    assert not list(stored.glob("*.exe"))
    if jax.config.jax_compilation_cache_dir:  # (the tests run with the cache on)
        # Compiled afresh (another program, so not in JAX's cache): stored.
        _programs.StoredProgram("test-hit", "hit", (), lambda x: program(x + 1.0))(np.ones(5))
        assert len(list(stored.glob("*.exe"))) == 1


def _jax_cache_hits(run):
    """`run()` and the number of JAX persistent-cache hits it made."""
    hits = []

    def listen(event, **kwargs):
        if event == "/jax/compilation_cache/cache_hits":
            hits.append(1)

    jax.monitoring.register_event_listener(listen)
    try:
        out = run()
    finally:
        jax.monitoring.unregister_event_listener(listen)
    return out, len(hits)


@pytest.mark.skipif(not jax.config.jax_compilation_cache_dir, reason="needs JAX's cache on")
@pytest.mark.parametrize("failure", ["load", "serialise"])
def test_a_program_that_cannot_be_kept_is_not_compiled_afresh_by_every_process(
        stored, monkeypatch, failure):
    """A stored program that this JAX cannot load, or one that cannot be serialised, ends in
    JAX's persistent cache (a stored program is otherwise kept out of it), so a later process
    (here: a new program object) reads it from there instead of compiling it afresh."""
    from jax.experimental import serialize_executable

    def program(x):
        return {"y": jax.numpy.sin(x) * 2.0 + {"load": 1.0, "serialise": 3.0}[failure]}

    def call():
        return _programs.StoredProgram("test-kept", failure, (), program)(np.ones(4))

    def broken(*args, **kwargs):
        raise RuntimeError("as another JAX would")

    if failure == "load":
        out = call()  # stored
        assert len(list(stored.glob("*.exe"))) == 1
        with monkeypatch.context() as m:
            m.setattr(serialize_executable, "deserialize_and_load", broken)
            again, hits = _jax_cache_hits(call)  # removed, compiled into JAX's cache
        assert not list(stored.glob("*.exe")) and hits == 0
    else:
        with monkeypatch.context() as m:
            m.setattr(serialize_executable, "serialize", broken)
            out = call()  # not stored: a marker says so
        assert not list(stored.glob("*.exe")) and list(stored.glob("*.unstorable"))
        again, hits = _jax_cache_hits(call)  # compiled into JAX's cache, not stored
        assert not list(stored.glob("*.exe")) and hits == 0
    later, hits = _jax_cache_hits(call)
    assert hits == 1 and not list(stored.glob("*.exe"))
    for result in (again, later):
        np.testing.assert_array_equal(result["y"], out["y"])


def test_stored_programs_run_on_a_machine_with_several_devices(tmp_path):
    """With two devices (forced host devices), the stored compiled program is loaded for the
    default device and inputs committed to the other are moved (as `jax.jit` moves them)."""
    script = (
        "import jax, jaxdyn as jd\n"
        "jax.config.update('jax_enable_x64', True)\n"
        f"jd.enable_compilation_cache({str(tmp_path)!r})\n"
        "sc = jd.Scene(jd.FallingRod(length=1.0, mass=1.0, g=9.81))\n"
        "y = jax.device_put(sc.state(theta=0.1), jax.devices()[-1])\n"
        "a, b = jd.simulate(sc, sc.state(theta=0.1), 10.0), jd.simulate(sc, y, 10.0)\n"
        "print(len(jax.devices()), repr(float(a.t_final)), repr(float(b.t_final)))\n"
    )
    env = host_devices_env(2)
    outs = []
    for _ in range(2):  # compiled and stored, then loaded
        proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                              env=env, timeout=300)
        assert proc.returncode == 0, proc.stderr[-2000:]
        outs.append(proc.stdout.split())
    assert list((tmp_path / "jaxdyn-programs").glob("*.exe"))
    fall = float(jd.FallingRod(length=1.0, mass=1.0, g=9.81).fall_time(0.1, 0.0))
    for count, a, b in outs:
        assert count == "2" and a == b and abs(float(a) - fall) < 1e-7 * fall


@pytest.mark.filterwarnings("ignore:Error writing persistent compilation cache")
def test_an_unwritable_folder_or_a_damaged_file_costs_only_the_storing(stored, monkeypatch):
    """A folder that cannot be written (read-only, full) stores nothing and the program still
    runs; a damaged stored program is removed and the program compiled again."""
    _programs._version()
    monkeypatch.setattr(_programs, "_VERSION", uuid.uuid4().hex)
    y0 = SCENE.state(theta=0.3)
    fall = float(SCENE.body.fall_time(0.3, 0.0))

    def refuse(self, data):
        raise OSError(30, "Read-only file system")

    with monkeypatch.context() as m:
        m.setattr(type(stored), "write_bytes", refuse)
        calls = []
        program, leaves = _program(calls)
        out = program(leaves, y0, np.asarray(5.0))
        assert abs(float(out[0]) - fall) < 1e-7 * fall and not list(stored.iterdir())
    calls = []
    program, leaves = _program(calls)
    program(leaves, y0, np.asarray(5.0))
    (exe,) = stored.glob("*.exe")
    exe.write_bytes(exe.read_bytes()[:1000])  # truncated
    again, _ = _program(calls)
    out = again(leaves, y0, np.asarray(5.0))
    assert abs(float(out[0]) - fall) < 1e-7 * fall
    assert not exe.exists() or exe.stat().st_size > 1000


def test_a_stored_program_is_traceable_by_the_callers_transformations(stored, monkeypatch):
    """A stored compiled program is specialised to concrete inputs: called under the caller's
    `jit` or `grad` (a derived output of a traced trajectory), the same program is traced."""
    _programs._version()
    monkeypatch.setattr(_programs, "_VERSION", uuid.uuid4().hex)

    def program(x):
        return {"y": jax.numpy.sin(x) * 2.0}

    stored_program = _programs.StoredProgram("test-traced", "traced", (), program)
    x = np.linspace(0.0, 1.0, 4)
    stored_program(x)  # compiled and stored
    again = _programs.StoredProgram("test-traced", "traced", (), program)
    np.testing.assert_allclose(again(x)["y"], 2 * np.sin(x))  # the stored one, loaded
    assert list(stored.glob("*.exe"))
    np.testing.assert_allclose(jax.jit(lambda x: again(x)["y"])(x), 2 * np.sin(x))
    grad = jax.grad(lambda x: again(x)["y"].sum())(x)
    np.testing.assert_allclose(grad, 2 * np.cos(x))


@pytest.fixture
def compile_overrides(monkeypatch):
    """The XLA options each compilation of this test was given on top of JAX's (`None`
    where none: a program compiled with JAX's settings alone)."""
    from jax._src import compiler

    seen = []
    original = compiler.get_compile_options
    _programs.staged()  # (its one eager operation compiled before recording)

    def recording(*args, **kwargs):
        seen.append(dict(kwargs.get("env_options_overrides") or {}) or None)
        return original(*args, **kwargs)

    monkeypatch.setattr(compiler, "get_compile_options", recording)
    return seen


@pytest.mark.parametrize("on_disk", [True, False], ids=["stored", "cache-off"])
def test_a_light_program_is_compiled_cheaply_where_called_and_traced_as_usual(
        on_disk, stored, monkeypatch, compile_overrides):
    """A light program (`_programs`: a trajectory's summary and resampling, the momentum
    sphere's equilibria and critical rotor momenta) is compiled with XLA's cheap settings
    where it is called with concrete inputs, stored or not, and under a key of its own; under
    the caller's `jit` or `grad` it is traced into the caller's program (where `jax.jit`
    refuses options of its own), also where its concrete inputs are captured by a function
    being staged, and gives the same numbers throughout."""
    if not on_disk:
        monkeypatch.setattr(_programs, "_directory", lambda: None)

    def program(x):
        return {"y": jax.numpy.sin(x) * 2.0}

    light = _programs.StoredProgram("test-light", "light", (), program, light=True)
    usual = _programs.StoredProgram("test-light", "light", (), program)
    x = np.linspace(0.0, 1.0, 4)
    np.testing.assert_allclose(light(x)["y"], 2 * np.sin(x), rtol=1e-15)
    assert compile_overrides == [_programs._LIGHT]
    np.testing.assert_allclose(usual(x)["y"], 2 * np.sin(x), rtol=1e-15)
    assert compile_overrides[1:] == [None]
    assert len(list(stored.glob("*.exe"))) == (2 if on_disk else 0)  # (two keys)
    del compile_overrides[:]
    np.testing.assert_allclose(jax.jit(lambda x: light(x)["y"])(x), 2 * np.sin(x), rtol=1e-15)
    grad = jax.grad(lambda x: light(x)["y"].sum())(x)
    np.testing.assert_allclose(grad, 2 * np.cos(x), rtol=1e-15)
    # Concrete inputs captured by a function of the caller's that is being staged (this
    # signature's call already made: a compiled program where stored, else `jax.jit`).
    np.testing.assert_allclose(jax.jit(lambda s: light(x)["y"] * s)(3.0), 6 * np.sin(x),
                               rtol=1e-15)
    assert None in compile_overrides and _programs._LIGHT not in compile_overrides


@pytest.mark.optimized
def test_light_trajectory_programs_give_the_numbers_of_the_usual_ones(stored, monkeypatch,
                                                                      compile_overrides):
    """A trajectory's summary and resampling are light programs (one pass over the
    trajectory, once per run); its evaluation, called again and again, is not. They give what
    the same functions compiled as usual give, to round-off (the free body's closed-form
    reference included)."""
    monkeypatch.setattr(_solution, "_PROGRAMS", {})  # (this process's programs: none)
    scene = jd.Scene(jd.RigidBody(np.array([1.0, 2.0, 2.5])), attitude=True)
    y0 = scene.state(omega=[0.3, 1.1, -0.2], quaternion=[1.0, 0.0, 0.0, 0.0])
    traj = jd.simulate(scene, y0, 30.0, dense=True)
    del compile_overrides[:]
    samples = traj.resample(257)
    report = samples.report()
    at = np.linspace(0.0, 30.0, 11)
    values = traj.evaluate(at)
    assert compile_overrides.count(_programs._LIGHT) == 2, compile_overrides  # not evaluate's
    usual = jax.jit(_solution._summary_of)(samples)

    def compare(a, b):  # (the report's values are Python numbers and lists)
        assert isinstance(a, dict) == isinstance(b, dict)
        if isinstance(a, dict):
            assert a.keys() == b.keys()
            for k in a:
                compare(a[k], b[k])
        else:  # (errors: round-off apart)
            np.testing.assert_allclose(np.asarray(a, float), b, rtol=1e-12, atol=1e-15)

    compare(report, usual)
    ts, ys = jax.jit(_solution._resample_of, static_argnums=1)(traj, 257)
    np.testing.assert_allclose(samples.ts, ts, rtol=1e-15)
    for k in ys:
        np.testing.assert_allclose(samples.ys[k], ys[k], rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(values[k], jax.jit(_solution._evaluate_of)(traj, at)[k],
                                   rtol=1e-13, atol=1e-15)


def test_gradients_through_a_derived_output_with_programs_stored(stored):
    """`jax.grad` of a derived output of a run from a traced state (the scene concrete): the
    stored outputs program, a compiled one, has no derivative rule, so traced
    inputs trace the function itself (with programs stored this raised "No VJP is
    available"). Checked against central differences."""
    scene = jd.Scene(jd.RigidBody([1.0, 2.0, 3.0]))
    ts = np.linspace(0.0, 1.0, 5)

    def f(w):
        return jd.simulate(scene, scene.state(omega=w), 1.0, ts=ts).omega[-1, 0]

    w = np.array([0.3, 1.0, 0.2])
    f(w)  # (the outputs program stored, concrete)
    grad = np.asarray(jax.grad(f)(jax.numpy.asarray(w)))
    h = 1e-6
    fd = [(float(f(w + h * e)) - float(f(w - h * e))) / (2 * h) for e in np.eye(3)]
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-8)


def _traced_on(threads):
    """A small stored program that records the thread each tracing runs on."""
    import threading

    def scaled(x, y):
        threads.append(threading.current_thread().name)
        return {"sum": x * 2.0 + jax.numpy.sin(y), "n": x.shape[0]}

    return _programs.StoredProgram("test-scaled", "scaled", (), scaled)


def test_a_prepared_program_is_compiled_on_another_thread_while_one_compiles(stored):
    threads, calls = [], []
    prepared = _traced_on(threads)
    x, y = np.arange(3.0), np.asarray(0.5)
    # Prepared with other values of the same shapes: only the signature matters.
    prepared.prepare(np.zeros(3), np.asarray(9.0))
    assert threads == [] and len(_programs._QUEUE) == 1  # waits for a compilation to start
    program, leaves = _program(calls)
    program(leaves, SCENE.state(theta=0.2), np.asarray(5.0))  # compiles: starts the other
    out = prepared(x, y)
    assert threads == ["jaxdyn-prepare"] and not _programs._QUEUE  # traced there, once
    # Its own numbers (an independent route: NumPy), and stored for the next process.
    np.testing.assert_allclose(out["sum"], 2.0 * x + np.sin(0.5), rtol=1e-15)
    assert len(list(stored.glob("*.exe"))) == 2
    again = _traced_on(threads)
    again.prepare(x, y)  # stored already: read when called, nothing queued
    assert not _programs._QUEUE
    np.testing.assert_array_equal(again(x, y)["sum"], out["sum"])
    assert threads == ["jaxdyn-prepare"]


def test_a_prepared_program_called_first_or_under_other_settings_is_made_by_the_call(stored):
    threads, calls = [], []
    prepared = _traced_on(threads)
    x, y = np.arange(3.0), np.asarray(0.5)
    prepared.prepare(x, y)
    prepared(x, y)  # called before any compilation started: made here, dropped from the queue
    assert threads == ["MainThread"] and not _programs._QUEUE
    # Prepared under a setting of the caller's thread (here x64 off): the worker, which does
    # not share it, leaves the program to the call, made under the caller's setting.
    threads.clear()
    other = _traced_on(threads)
    with jax.enable_x64(False):
        other.prepare(np.arange(3.0, dtype=np.float32), np.asarray(0.5, np.float32))
        trigger = _traced_on(calls)  # another program compiled: starts the worker
        trigger(np.arange(4.0, dtype=np.float32), np.asarray(0.5, np.float32))
        out = other(np.arange(3.0, dtype=np.float32), np.asarray(0.5, np.float32))
    assert threads == ["MainThread"] and out["sum"].dtype == np.float32
    np.testing.assert_allclose(out["sum"], 2.0 * np.arange(3.0) + np.sin(0.5), rtol=1e-6)


def test_a_prepared_program_never_leaves_a_call_waiting(stored, monkeypatch):
    import threading

    x, y = np.arange(3.0), np.asarray(0.5)
    expected = 2.0 * x + np.sin(0.5)
    # Two threads call before any compilation started: each gets the program.
    threads, results = [], []
    prepared = _traced_on(threads)
    prepared.prepare(x, y)
    callers = [threading.Thread(target=lambda: results.append(prepared(x, y)["sum"]),
                                daemon=True) for _ in range(2)]
    for c in callers:
        c.start()
    for c in callers:
        c.join(timeout=60)
    assert not any(c.is_alive() for c in callers) and len(results) == 2
    for r in results:
        np.testing.assert_allclose(r, expected, rtol=1e-15)
    # A call interrupted while it compiles the program itself (Ctrl-C in a notebook): the
    # next call compiles it.
    again = _traced_on([])
    again.prepare(np.zeros(4), y)
    with monkeypatch.context() as m, pytest.raises(KeyboardInterrupt):
        m.setattr(again, "_ready", lambda *a: (_ for _ in ()).throw(KeyboardInterrupt))
        again(np.zeros(4), y)
    np.testing.assert_allclose(again(np.arange(4.0), y)["sum"],
                               2.0 * np.arange(4.0) + np.sin(0.5), rtol=1e-15)
    # No thread to be had when a compilation starts: the prepared program's call makes it,
    # and the program that was compiling is still stored.
    monkeypatch.setattr(_programs, "_VERSION", uuid.uuid4().hex)
    late = _traced_on([])
    late.prepare(np.zeros(5), y)

    def no_thread(*a, **k):
        raise RuntimeError("can't start new thread")

    calls, before = [], len(list(stored.glob("*.exe")))
    program, leaves = _program(calls)
    with monkeypatch.context() as m:
        m.setattr(threading.Thread, "start", no_thread)
        program(leaves, SCENE.state(theta=0.2), np.asarray(5.0))
    assert calls == [1] and len(list(stored.glob("*.exe"))) == before + 1
    np.testing.assert_allclose(late(np.arange(5.0), y)["sum"],
                               2.0 * np.arange(5.0) + np.sin(0.5), rtol=1e-15)


def test_preparations_a_function_did_not_use_are_dropped_when_it_ends(stored):
    x, y = np.arange(3.0), np.asarray(0.5)
    threads = []
    prepared = _traced_on(threads)

    @_programs.cancels_unused_preparations
    def interrupted_fit():
        prepared.prepare(x, y)
        assert len(_programs._QUEUE) == 1
        raise ValueError("stopped before its summaries")

    with pytest.raises(ValueError):
        interrupted_fit()
    assert not _programs._QUEUE  # nothing left for a later compilation to start
    prepared.prepare(x, y)  # a later fit's preparation of the signature is queued anew
    assert len(_programs._QUEUE) == 1
    _programs._QUEUE[0].cancel()
    calls = []
    program, leaves = _program(calls)
    program(leaves, SCENE.state(theta=0.2), np.asarray(5.0))
    assert threads == []  # not compiled for nothing on a worker
    np.testing.assert_allclose(prepared(x, y)["sum"], 2.0 * x + np.sin(0.5), rtol=1e-15)
    assert threads == ["MainThread"]


@pytest.fixture
def compiled_on():
    """The names of the programs XLA compiles during the test, with the thread of each."""
    import threading

    seen = []

    def listen(event, duration, fun_name=None, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            seen.append((str(fun_name).removeprefix("jit(").split("_")[0],
                         threading.current_thread().name))

    jax.monitoring.register_event_duration_secs_listener(listen)
    yield seen
    jax.monitoring.unregister_event_duration_listener(listen)


@pytest.mark.parametrize("samples", [None, 17])
def test_a_run_prepares_its_resampling_and_summary_while_it_compiles(stored, monkeypatch,
                                                                      compiled_on, samples):
    # `jaxdyn run`: as the run's program is lowered, its resampling (`samples`) and summary
    # are prepared from the shapes of its outputs, and compile on worker threads while this
    # thread compiles the run; the calls that follow wait for them instead of compiling.
    monkeypatch.setattr(_simulate, "_STRUCTURES", {})  # (this process's programs: none)
    monkeypatch.setattr(_simulate, "_LAST", [_simulate._NO_SCENE])
    monkeypatch.setattr(_solution, "_PROGRAMS", {})
    scene = jd.Scene(jd.RigidBody(np.array([1.0, 2.0, 2.5])))
    y0 = scene.state(omega=[0.3, 1.1, -0.2])
    options = dict(dense=True) if samples else dict(ts=np.linspace(0.0, 4.0, 9))
    seen = compiled_on
    shapes = []

    def prepare(shape):
        shapes.append(shape)
        _solution.prepare_report(shape, samples)

    with _simulate.then_prepare(prepare):
        traj = jd.simulate(scene, y0, 4.0, **options)
    if samples:
        traj = traj.resample(samples)
    report = traj.report()
    programs = {name: thread for name, thread in seen if name in ("simulate", "resample",
                                                                  "summary")}
    assert programs == {"simulate": "MainThread", "summary": "jaxdyn-prepare",
                        **({"resample": "jaxdyn-prepare"} if samples else {})}, seen
    assert len([n for n, _ in seen if n in programs]) == len(programs)  # each compiled once
    assert not _programs._QUEUE and len(shapes) == 1
    assert isinstance(shapes[0].t_final, jax.ShapeDtypeStruct) and shapes[0].scene is scene
    # The numbers: the torque-free closed form (an independent route), and the summary of
    # equinox's filtered program (not the prepared one; compiled as usual where the prepared
    # one is light, so equal to round-off).
    exact = scene.body.exact_omega(y0["omega"], traj.t_final)
    np.testing.assert_allclose(report["omega_final"], exact, rtol=1e-7)
    again = jax.tree.map(np.asarray, _solution._summary_filtered(traj))
    np.testing.assert_allclose(report["omega_final"], again["omega_final"], rtol=1e-13)
    np.testing.assert_allclose(report["reference"]["omega_final"],
                               again["reference"]["omega_final"], rtol=1e-13)
    # A second run of the structure compiles nothing and calls nothing back.
    with _simulate.then_prepare(prepare):
        jd.simulate(scene, y0, 4.0, **options)
    assert len(shapes) == 1


def test_a_failing_preparation_costs_the_run_nothing(stored, monkeypatch):
    monkeypatch.setattr(_simulate, "_STRUCTURES", {})
    monkeypatch.setattr(_simulate, "_LAST", [_simulate._NO_SCENE])
    monkeypatch.setattr(_solution, "_PROGRAMS", {})
    y0 = SCENE.state(theta=0.3)

    called = []

    def broken(shape):
        called.append(shape)
        raise RuntimeError("a bug in a preparation")

    with _simulate.then_prepare(broken):
        traj = jd.simulate(SCENE, y0, 5.0, dense=True)
    assert len(called) == 1
    np.testing.assert_allclose(traj.resample(5).report()["impact_time"],
                               SCENE.body.fall_time(0.3), rtol=1e-8)
    assert not _programs._QUEUE


def test_when_lowered_calls_back_once_for_the_next_program_compiled(stored):
    # The callback belongs to the next stored program this thread lowers, not the ones
    # after; `when_lowered(None)` inside leaves it in place.
    seen = []
    first, second = _traced_on([]), _traced_on([])
    x, y = np.arange(3.0), np.asarray(0.5)
    with _programs.when_lowered(seen.append), _programs.when_lowered(None):
        first(x, y)
        second(np.arange(4.0), y)
    assert len(seen) == 1
    assert seen[0]["sum"].shape == (3,) and isinstance(seen[0]["sum"], jax.ShapeDtypeStruct)
    assert seen[0]["n"].shape == () and seen[0]["n"].weak_type  # (its weak type kept)


def _uncached(caplog, run):
    """The programs that `run` compiled but JAX's persistent cache refused (a host callback)."""
    with caplog.at_level("DEBUG", logger="jax"):
        caplog.clear()
        out = run()
    return [r.getMessage() for r in caplog.records
            if re.search("Not writing persistent cache entry .* host callbacks",
                         r.getMessage())], out


def test_fixed_steps_first_steps_and_implicit_solvers_with_samples_are_cacheable(caplog):
    """The programs of runs that give a step (`dt0`: fixed steps, or the first step of an
    adaptive solver) or sample an implicit solver's run hold no host callback: diffrax checks
    the sign of a traced `dt0` and the order of traced `SaveAt(ts)` with equinox's runtime
    errors, so `dt0` is held by the controller (`jaxdyn._solvers._fixed`), checked on the host,
    and the samples are written from the steps. Same steps and states as diffrax's own
    `ConstantStepSize` with `dt0`, and as the samples diffrax saves (under the caller's `jit`)."""
    import diffrax as dfx

    inertia = np.array([1.0, 2.0, 3.0])
    scene = jd.Scene(jd.RigidBody(inertia))
    w0 = np.array([0.3, 1.0, 0.2])
    y0 = scene.state(omega=w0)
    ts = np.linspace(0.0, 2.0, 9)
    h = float(np.random.default_rng().uniform(0.01, 0.02))  # (a new program each time)

    def euler(t, w, args):
        i = inertia
        return jax.numpy.stack([(i[1] - i[2]) / i[0] * w[1] * w[2],
                                (i[2] - i[0]) / i[1] * w[2] * w[0],
                                (i[0] - i[1]) / i[2] * w[0] * w[1]])

    runs = {
        "fixed steps": lambda: jd.simulate(scene, y0, 2.0, solver=dfx.Heun(), dt0=h,
                                           stepsize_controller=dfx.ConstantStepSize()),
        "RK4 with a step": lambda: jd.simulate(scene, y0, 2.0, solver=jd.RK4(), dt0=h),
        "splitting": lambda: jd.simulate(scene, y0, 2.0, solver=jd.RotationSplitting(4),
                                         dt0=h, ts=ts),
        "first step": lambda: jd.simulate(scene, y0, 2.0, dt0=h, rtol=1e-9, ts=ts),
        "implicit, sampled": lambda: jd.simulate(scene, y0, 2.0, solver=dfx.Kvaerno5(),
                                                 rtol=1e-9 + h * 1e-12, ts=ts),
    }
    for name, run in runs.items():
        refused, _ = _uncached(caplog, run)
        assert not refused, (name, refused)
    # The control: a run that reports its progress holds a callback, and is seen to.
    refused, _ = _uncached(caplog, lambda: jd.simulate(scene, y0, 2.0, progress=True))
    assert refused

    traj = runs["fixed steps"]()
    ref = dfx.diffeqsolve(dfx.ODETerm(euler), dfx.Heun(), 0.0, 2.0, h, jax.numpy.asarray(w0),
                          stepsize_controller=dfx.ConstantStepSize(), max_steps=10_000)
    assert int(traj.stats["num_steps"]) == int(ref.stats["num_steps"]) == int(np.ceil(2 / h))
    np.testing.assert_allclose(traj.y_final["omega"], ref.ys[-1], rtol=1e-14, atol=1e-15)
    # The samples written from the implicit solver's steps against diffrax's `SaveAt(ts)`
    # (the path of a run under the caller's `jit`, whose sample times are traced).
    traj = runs["implicit, sampled"]()
    traced = jax.jit(lambda ts: jd.simulate(scene, y0, 2.0, solver=dfx.Kvaerno5(),
                                            rtol=1e-9 + h * 1e-12, ts=ts))(ts)
    assert int(traj.stats["num_steps"]) == int(traced.stats["num_steps"])
    np.testing.assert_allclose(traj.ys["omega"], traced.ys["omega"], rtol=1e-12, atol=1e-14)
    # And against an independent route: the closed form, within the tolerance.
    exact = np.asarray(jd.torque_free_omega(inertia, w0, ts))
    np.testing.assert_allclose(traj.ys["omega"], exact, atol=1e-6)


def test_a_step_is_checked_where_it_is_known_and_inside_the_program_where_it_is_traced():
    scene = jd.Scene(jd.RigidBody([1.0, 2.0, 3.0]))
    y0 = scene.state(omega=[0.3, 1.0, 0.2])
    import diffrax as dfx

    for bad in (-0.01, 0.0, float("nan"), float("inf")):
        with pytest.raises(jd.ParameterError, match=r"dt0=.*: must be a positive finite step"):
            jd.simulate(scene, y0, 1.0, solver=dfx.Euler(), dt0=bad)
    with pytest.raises(jd.ParameterError, match=r"dt0='x': expected a number"):
        jd.simulate(scene, y0, 1.0, solver=dfx.Euler(), dt0="x")
    with pytest.raises(jd.ParameterError, match=r"dt0 has shape \(2,\)"):
        jd.simulate(scene, y0, 1.0, solver=dfx.Euler(), dt0=[0.1, 0.2])
    # A step traced by the caller's `grad` alone (the rest concrete) is checked in the program.
    with pytest.raises(Exception, match="dt0: must be a positive finite step"):
        jax.grad(lambda h: jd.simulate(scene, y0, 1.0, solver=dfx.Euler(), dt0=h,
                                       max_steps=500).y_final["omega"][0])(-0.01)
    run = jax.jit(lambda h: jd.simulate(scene, y0, 1.0, solver=dfx.Euler(), dt0=h).y_final)
    assert np.all(np.isfinite(run(0.01)["omega"]))
    with pytest.raises(Exception, match="dt0: must be a positive finite step"):
        jax.block_until_ready(run(-0.01))


def test_a_solver_without_an_error_estimate_takes_fixed_steps():
    """`jaxdyn.RK4` is an explicit Runge-Kutta method to diffrax but estimates no error: given
    `dt0` alone it takes fixed steps (an adaptive controller saw zero error and grew the step
    tenfold at each step: 5 steps over 20 s, an error of 1e34), and an adaptive controller is
    refused."""
    import diffrax as dfx

    inertia, w0 = np.array([1.0, 2.0, 3.0]), np.array([0.3, 1.0, 0.2])
    scene = jd.Scene(jd.RigidBody(inertia))
    y0 = scene.state(omega=w0)
    traj = jd.simulate(scene, y0, 20.0, solver=jd.RK4(), dt0=0.01)
    assert int(traj.stats["num_steps"]) == 2000
    exact = np.asarray(jd.torque_free_omega(inertia, w0, 20.0))
    assert np.max(np.abs(np.asarray(traj.y_final["omega"]) - exact)) < 1e-8
    with pytest.raises(jd.ParameterError, match="RK4 has no error estimate"):
        jd.simulate(scene, y0, 20.0, solver=jd.RK4(), dt0=0.01,
                    stepsize_controller=dfx.PIDController(rtol=1e-6, atol=1e-9))
    with pytest.raises(jd.ParameterError, match="RK4 takes fixed steps: give dt0"):
        jd.simulate(scene, y0, 20.0, solver=jd.RK4())


def test_padded_lengths_are_few_and_waste_at_most_a_fifth():
    from jaxdyn._padded import padded_length

    lengths = [padded_length(n) for n in range(1, 1 << 14)]
    assert all(p >= max(n, 16) for n, p in enumerate(lengths, 1))
    assert all(p <= 1.25 * n for n, p in enumerate(lengths, 1) if n > 16)
    assert len(set(lengths)) == 1 + 4 * 10  # 16, then four per octave up to 2^14
    assert padded_length(0) == 16 and padded_length(10**6) == 1 << 20


def test_a_new_number_of_times_reuses_the_evaluate_program():
    # `traj.evaluate` pads the times to one of a few lengths (`jaxdyn._padded`), so a new
    # number of times (a slider over the resolution) lowers only the small program that cuts
    # the padding off; the values are those of the same evaluation traced at that length.
    scene = jd.Scene(jd.RigidBody(inertia=[1.0, 2.0, 3.0]))
    traj = jd.simulate(scene, scene.state(omega=[0.3, 1.0, 0.2]), 4.0, dense=True)
    traj.evaluate(np.linspace(0.0, 4.0, 100))  # padded to 112
    (program,) = [p for key, p in _solution._PROGRAMS.items() if key[0] == "evaluate"
                  and key[1] == jax.tree_util.tree_structure(traj)]
    signatures = len(program.calls)
    traced = jax.jit(lambda tr, t: tr.evaluate(t))
    for n in (101, 106, 112):
        t = np.linspace(-0.5, 4.5, n)  # (some outside the run: nan there, as traced)
        with new_programs() as compiled:
            got = traj.evaluate(t)
        assert len(compiled) == 1 and got["omega"].shape == (n, 3)  # the cut alone
        np.testing.assert_allclose(got["omega"], traced(traj, t)["omega"], rtol=1e-14,
                                   atol=1e-15)
    assert len(program.calls) == signatures
    with new_programs() as compiled:  # positive control: past the padded length
        traj.evaluate(np.linspace(0.0, 4.0, 113))
    assert len(compiled) == 2 and len(program.calls) == signatures + 1


def test_dense_output_calls_trace_once_per_structure_and_shape():
    # `traj.evaluate` and `traj.resample` are one compiled program per trajectory structure and
    # shape of times: after the first call, a new run of the same scene (other values) traces
    # and compiles nothing, and the programs give what the same functions give traced.
    scene = jd.Scene(jd.RigidBody(inertia=[1.0, 2.0, 3.0]))
    first = jd.simulate(scene, scene.state(omega=[0.3, 1.0, 0.2]), 4.0, dense=True)
    times = np.linspace(0.0, 4.0, 7)
    for t in (1.5, times):
        first.evaluate(t)
    first.resample(9)
    traces = []

    def listener(name, *args, **kwargs):
        if name in ("/jax/core/compile/jaxpr_trace_duration",
                    "/jax/core/compile/jaxpr_to_mlir_module_duration"):
            traces.append(name)

    again = jd.simulate(scene, scene.state(omega=[0.1, 2.0, -0.4]), 4.0, dense=True)
    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        at_one, at_times = again.evaluate(1.5), again.evaluate(times)
        resampled = again.resample(9)
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert traces == []
    traced = jax.jit(lambda tr: (tr.evaluate(1.5), tr.evaluate(times), tr.resample(9).ys))
    ref_one, ref_times, ref_resampled = traced(again)
    np.testing.assert_allclose(at_one["omega"], ref_one["omega"], rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(at_times["omega"], ref_times["omega"], rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(resampled.ys["omega"], ref_resampled["omega"], rtol=1e-14,
                               atol=1e-15)
    np.testing.assert_allclose(resampled.ts, np.linspace(0.0, 4.0, 9), rtol=1e-15)
    assert np.all(np.isnan(again.evaluate(np.array([-1.0, 5.0]))["omega"]))  # outside the run
    assert any(key[0] == "evaluate" for key in _solution._PROGRAMS)  # one program, not eager
    # The caller's array is copied: changed right after the call, the result is unchanged.
    many = np.linspace(0.0, 4.0, 200_000)
    result = again.evaluate(many)
    many[:] = -1.0
    np.testing.assert_array_equal(result["omega"],
                                  again.evaluate(np.linspace(0.0, 4.0, 200_000))["omega"])
    # Times in a list that holds traced values (under `grad`): traced, as before.
    slope = jax.grad(lambda s: again.evaluate([s, 0.1])["omega"][0, 1])(1.5)
    np.testing.assert_allclose(slope, at_one["omega"][2] * (3.0 - 1.0) / 2.0
                               * at_one["omega"][0], rtol=1e-6)
    for bad in (None, [0.5, None], "1.0"):
        with pytest.raises(jd.ParameterError, match="t"):
            again.evaluate(bad)
