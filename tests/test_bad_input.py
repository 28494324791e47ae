"""Bad input: every public entry point, through the Python API and through the command.

Each case must fail early with a message naming the field, the value and what is allowed; the
command exits with status 2 and one line; values only known inside `jit` fail at run time with a
message naming the field (`eqx.error_if`). Nothing returns a silently wrong number.
"""

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_cli import run_cli

import jaxdyn as jd

nan, inf = float("nan"), float("inf")
BODY = jd.RigidBody([1.0, 2.0, 3.0])
SCENE = jd.Scene(BODY)
Y0 = SCENE.state(omega=[0.1, 1.0, 0.1])
ROD = jd.FallingRod()

API = [
    # bodies
    ("FallingRod(length=-1)", lambda: jd.FallingRod(length=-1.0), "length=-1: must be positive"),
    ("FallingRod(mass=nan)", lambda: jd.FallingRod(mass=nan), "mass=nan: must be positive"),
    ("FallingRod(g=inf)", lambda: jd.FallingRod(g=inf), "g=inf: must be positive"),
    ("FallingRod(length='long')", lambda: jd.FallingRod(length="long"),
     "length='long': expected a number"),
    ("FallingRod(length=[1, 2])", lambda: jd.FallingRod(length=[1.0, 2.0]),
     "length has shape (2,): expected shape ()"),
    ("RigidBody negative", lambda: jd.RigidBody([-1.0, 2.0, 2.0]), "must be positive"),
    ("RigidBody triangle", lambda: jd.RigidBody([1.0, 2.0, 10.0]), "triangle inequality"),
    ("RigidBody nan", lambda: jd.RigidBody([nan, 2.0, 2.0]), "must be positive and finite"),
    ("RigidBody shape", lambda: jd.RigidBody([1.0, 2.0]),
     "expected 3 principal moments or a 3x3 tensor"),
    ("RigidBody non-symmetric", lambda: jd.RigidBody([[1, 0.5, 0], [0, 1, 0], [0, 0, 1]]),
     "must be symmetric"),
    ("RigidBody tensor triangle", lambda: jd.RigidBody(np.diag([1.0, 1.0, 5.0])),
     "triangle inequality"),
    ("RigidBody text", lambda: jd.RigidBody("heavy"), "expected a number"),
    # effects
    ("Rotor nan", lambda: jd.Rotor([0.0, nan, 0.0]), "rotor.momentum=[ 0., nan,  0.]: must be "
     "finite"),
    ("Rotor shape", lambda: jd.Rotor([1.0, 2.0]), "rotor.momentum has shape (2,)"),
    ("ExternalTorque frame", lambda: jd.ExternalTorque([0.0, 0.0, 1.0], frame="galactic"),
     "torque.frame='galactic': allowed are 'body', 'inertial'"),
    ("ExternalTorque feedback", lambda: jd.ExternalTorque([0.0, 0.0, 1.0], feedback=True),
     "needs a function"),
    ("GravityGradient rate", lambda: jd.GravityGradient(orbit_rate=-1.0),
     "gravity-gradient.orbit_rate=-1: must be positive"),
    ("Wheels none", lambda: jd.Wheels(axes=np.zeros((0, 3)), inertia=np.zeros(0)),
     "wheels.axes has shape (0, 3): expected (N, 3) with N >= 1"),
    ("Thrusters none", lambda: jd.Thrusters(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)),
     "thrusters.positions has shape (0, 3): expected (N, 3) with N >= 1"),
    # scenes and states
    ("Scene body", lambda: jd.Scene("a rod"), "expected a jaxdyn body"),
    ("Scene effect", lambda: jd.Scene(BODY, ("spin",)), "expected jaxdyn effects"),
    ("Scene rod effect", lambda: jd.Scene(ROD, (jd.Rotor([0.0, 0.0, 1.0]),)),
     "cannot act on a falling-rod"),
    ("Scene rod attitude", lambda: jd.Scene(ROD, attitude=True), "has no 3-D attitude"),
    ("state missing", lambda: SCENE.state(), "omega is required"),
    ("state unknown", lambda: SCENE.state(omega=[0.0, 0.0, 1.0], spin=1.0),
     "unknown state variables ['spin']"),
    ("state shape", lambda: SCENE.state(omega=[1.0]), "omega has shape (1,): expected shape (3,)"),
    ("rod theta", lambda: jd.Scene(ROD).state(theta=2.0), "theta=2: must be finite and within"),
    ("rod theta nan", lambda: jd.Scene(ROD).state(theta=nan), "theta=nan"),
    ("replace unknown", lambda: SCENE.replace(mass=1.0), "unknown parameter(s) ['mass']"),
    ("replace invalid", lambda: SCENE.replace(inertia=[1.0, 1.0, 3.0]), "triangle inequality"),
    # simulate
    ("simulate t1 < t0", lambda: jd.simulate(SCENE, Y0, 1.0, t0=2.0),
     "t1=1: must be greater than t0=2"),
    ("simulate t1 nan", lambda: jd.simulate(SCENE, Y0, nan), "times must be finite"),
    ("simulate ts outside", lambda: jd.simulate(SCENE, Y0, 1.0, ts=[0.0, 2.0]),
     "must be increasing and within [t0, t1]"),
    ("simulate ts decreasing", lambda: jd.simulate(SCENE, Y0, 1.0, ts=[0.5, 0.1]),
     "must be increasing"),
    ("simulate rtol", lambda: jd.simulate(SCENE, Y0, 1.0, rtol=-1e-8),
     "rtol=-1e-08: must be positive"),
    ("simulate max_steps", lambda: jd.simulate(SCENE, Y0, 1.0, max_steps=0),
     "max_steps=0: must be a positive integer"),
    ("simulate y0 keys", lambda: jd.simulate(SCENE, {"theta": 0.1}, 1.0),
     "y0 has variables ['theta']: this scene integrates ['omega']"),
    ("simulate y0 nan", lambda: jd.simulate(SCENE, {"omega": jnp.array([nan, 0.0, 1.0])}, 1.0),
     "y0['omega']=[nan,  0.,  1.]: must be finite"),
    ("simulate y0 type", lambda: jd.simulate(SCENE, [0.1, 1.0, 0.1], 1.0),
     "expected a state dict"),
    ("simulate scene", lambda: jd.simulate(BODY, Y0, 1.0), "expected a jaxdyn.Scene"),
    ("simulate y0 narrower than the scene",
     lambda: jd.simulate(SCENE, {"omega": np.array([0.1, 1.0, 0.1], np.float32)}, 1.0),
     "y0['omega'] is float32 but its derivative under this scene is float64 (the scene holds "
     "float64 values: body.inertia): give y0['omega'] in float64"),
    ("simulate y0 mixed precisions",
     lambda: jd.simulate(jd.Scene(BODY, attitude=True),
                         {"omega": np.array([0.1, 1.0, 0.1], np.float32),
                          "quaternion": np.array([1.0, 0.0, 0.0, 0.0])}, 1.0),
     "y0['omega'] is float32 but its derivative under this scene is float64"),
    ("ensemble y0 narrower than the scene",
     lambda: jd.ensemble(SCENE, {"omega": np.array([0.1, 1.0, 0.1], np.float32)}, 1.0, n=2),
     "y0['omega'] is float32 but its derivative under this scene is float64"),
    ("evaluate shape", lambda: jd.simulate(SCENE, Y0, 1.0, dense=True).evaluate([[0.5]]),
     "t has shape (1, 1): expected a time or a 1-D array of times"),
    # closed forms and helpers
    ("torque_free_omega inertia", lambda: jd.torque_free_omega([1.0, 2.0, 9.0], [1, 0, 0], 1.0),
     "triangle inequality"),
    ("torque_free_omega omega", lambda: jd.torque_free_omega([1.0, 2.0, 3.0], [nan, 0, 0], 1.0),
     "omega0=[nan,  0.,  0.]: must be finite"),
    ("torque_free_period", lambda: jd.torque_free_period([0.0, 2.0, 3.0], [1.0, 0, 0]),
     "must be positive"),
    ("polhode num", lambda: jd.polhode([1.0, 2.0, 3.0], [1.0, 0.1, 0.1], num=1),
     "num=1: must be an integer >= 2"),
    ("separatrix_curves", lambda: jd.separatrix_curves([2.0, 2.0, 2.0]), "no intermediate axis"),
    ("fall_time theta0", lambda: ROD.fall_time(2.0), "theta0=2: must be finite and within"),
    ("rate theta_dot0", lambda: ROD.rate(1.0, 0.1, nan), "theta_dot0=nan: must be finite"),
    # scene files
    ("load_scene unknown", lambda: jd.load_scene("no-such-scene"), "not a built-in scene"),
    ("load_scene override", lambda: jd.load_scene("falling-rod", {"spin": 1.0}),
     "unknown parameter 'spin'"),
    ("load_scene type", lambda: jd.load_scene("falling-rod", {"length": "long"}),
     "length='long': expected a positive finite number (m)"),
]


@pytest.mark.parametrize("call, expected", [c[1:] for c in API], ids=[c[0] for c in API])
def test_python_api_rejects_bad_input(call, expected):
    with pytest.raises(jd.ParameterError) as info:
        call()
    assert expected in str(info.value)


def _final(inertia):
    scene = SCENE.replace(inertia=inertia)
    return jd.simulate(scene, scene.state(omega=[0.1, 1.0, 0.1]), 1.0).y_final["omega"]


def test_traced_invalid_parameter_fails_at_run_time_naming_it():
    final = eqx.filter_jit(_final)
    assert jnp.all(jnp.isfinite(final(jnp.array([1.0, 2.0, 2.5]))))
    with pytest.raises(eqx.EquinoxRuntimeError,
                       match="invalid inertia: each principal moment must not"):
        final(jnp.array([1.0, 2.0, 10.0]))
    # Under plain jax.jit equinox cannot raise its own type, but the message still comes through.
    with pytest.raises((RuntimeError, ValueError), match="invalid inertia"):
        jax.jit(_final)(jnp.array([1.0, 2.0, 10.0]))


def test_traced_invalid_state_fails_at_run_time():
    run = eqx.filter_jit(lambda w: jd.simulate(SCENE, {"omega": w}, 1.0).y_final["omega"])
    with pytest.raises(eqx.EquinoxRuntimeError, match=r"invalid y0\['omega'\]: must be finite"):
        run(jnp.array([nan, 1.0, 0.0]))


def test_solver_choice_errors_are_clear():
    with pytest.raises(RuntimeError, match="step budget"):
        jd.simulate(SCENE, Y0, 100.0, solver=dfx.Euler(),
                    stepsize_controller=dfx.ConstantStepSize(), dt0=1e-3, max_steps=100)


BAD_TOML = {
    "malformed": ("body = 'rigid-body\n", "malformed TOML"),
    "unknown key": ('body = "rigid-body"\ncolour = 3\n', "unknown key"),
    "unknown body": ('body = "pendulum"\n', "body='pendulum': expected the name of a body"),
    "body as a table": ('[body]\nkind = "rigid-body"\ninertia = [1, 2, 3]\n',
                        "the body's values go in the [parameters] table"),
    "unknown parameter": ('body = "falling-rod"\n[parameters]\nlength = 1.0\ntheta0 = 0.1\n'
                          'spin = 2\n', "unknown parameter 'spin'"),
    "wrong type": ('body = "falling-rod"\n[parameters]\nlength = "long"\ntheta0 = 0.1\n',
                   "length='long': expected a positive finite number (m)"),
    "unknown effect": ('body = "rigid-body"\n[parameters]\ninertia = [1, 2, 3]\n'
                       'omega0 = [1, 0, 0]\n[[effects]]\ntype = "magnet"\n', "magnet"),
}


@pytest.mark.parametrize("case", sorted(BAD_TOML))
def test_bad_scene_files(capsys, tmp_path, case):
    text, expected = BAD_TOML[case]
    path = tmp_path / "bad.toml"
    path.write_text(text)
    status, out, err = run_cli(capsys, "run", str(path))
    assert status == 2 and out == ""
    assert expected in err and len(err.strip().splitlines()) == 1


BAD_SETS = [
    (["--set", "length=-1"], "length=-1: expected a positive finite number (m)"),
    (["--set", "mass=nan"], "mass=nan: expected a positive finite number (kg)"),
    (["--set", "g=inf"], "g=inf: expected a positive finite number (m/s^2)"),
    (["--set", "theta0=2"], "within [-pi/2, pi/2]"),
    (["--set", "theta0=abc"], "theta0='abc': expected a finite number (rad)"),
    (["--set", "spin=2"], "unknown parameter 'spin'"),
    (["--set", "length"], "expected NAME=VALUE"),
    (["--t1", "-1"], "t1=-1: expected a positive finite number (s)"),
    (["torque-free", "--set", "inertia=1,2,10"], "triangle inequality"),
    (["torque-free", "--set", "inertia=1,2"], "inertia=[1., 2.]: expected 3 finite numbers or 9"),
    (["torque-free", "--set", "inertia=1,0.5,0,0,1,0,0,0,1"], "must be symmetric"),
    (["torque-free", "--set", "inertia=-1,2,2"], "must be positive"),
    (["torque-free", "--set", "omega0=1,2"], "omega0=[1., 2.]: expected 3 finite numbers (rad/s)"),
    (["torque-free", "--set", "rotor.momentum=1,2,3"], "has no 'rotor' effect"),
    (["no-such-scene"], "not a built-in scene or a file"),
    (["--frobnicate"], "unrecognized arguments"),
]


@pytest.mark.parametrize("argv, expected", BAD_SETS, ids=[" ".join(a) for a, _ in BAD_SETS])
def test_bad_values_exit_2_with_one_line(capsys, argv, expected):
    status, out, err = run_cli(capsys, "run", *argv)
    assert status == 2 and out == ""
    assert expected in err, err
    assert len(err.strip().splitlines()) == 1




@pytest.mark.parametrize("mode", ["adaptive", "vmap"])
def test_an_ensemble_refuses_fixed_steps_by_name(mode):
    # Every ensemble mode steps adaptively: a fixed-step solver (given dt0) is refused naming
    # it (in vmap mode it crashed with a raw pytree-structure ValueError from the controller).
    y0 = SCENE.state(omega=[0.3, 1.0, 0.2])
    batch = {k: jnp.stack([v, v]) for k, v in y0.items()}
    for solver in (dfx.Euler(), jd.RK4()):
        with pytest.raises(jd.ParameterError, match=f"solver {type(solver).__name__} takes "
                           "fixed steps: an ensemble's trajectories take adaptive steps"):
            jd.ensemble(SCENE, batch, 1.0, solver=solver, dt0=0.01, mode=mode)
