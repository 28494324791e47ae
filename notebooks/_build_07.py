"""Build notebook 07 (run: `python notebooks/_build_07.py`); see `_build.py`."""

from _build import HERE, IMPORTS, X64, build

SPIN = [
    ("md", r"""
# Spin stabilisation and dissipation: dual spinners, reaction wheels and the major-axis rule"""),
    ("md", r"""
Where the torque-free lecture stops, spacecraft begin: a spinning rotor inside the body can make
a spin about the unstable intermediate axis stable (a *dual spinner*), motor-driven reaction wheels
can stop a tumble or point the body anywhere, and energy dissipation turns every spin into a spin
about the axis of largest inertia, as Explorer 1 found out in 1958. Each device is an effect with
its own state (the wheel's axial angular momentum), present only when a scene declares it. Each
section checks a conservation law or a closed-form condition."""),
    ("code", IMPORTS),
    ("code", X64),
    ("md", r"""
## The model

A wheel $i$ spins about a fixed axis $g_i$ with axial inertia $J_i$; its state is its absolute
axial momentum $h_i = J_i(\Omega_i + g_i\cdot\omega)$, which changes only by the torque $u_i$
applied to it (motor torque minus viscous friction). With $I$ the body's inertia excluding the
wheels' axial inertia,

$$I\dot\omega = \Big(I\omega + \sum_i h_i g_i\Big)\times\omega - \sum_i u_i g_i,
\qquad \dot h_i = u_i .$$

The total angular momentum $I\omega + \sum h_i g_i$ is conserved; the kinetic energy
$\tfrac12\omega\cdot I\omega + \sum h_i^2/2J_i$ changes at the rate $\sum u_i\Omega_i$."""),
    ("md", r"""
## 1. A dual spinner: a rotor stabilises the intermediate axis

Body $I = (1, 2, 3)$ spinning at $w = 2$ rad/s about axis 2, with a rotor along axis 2. A spin
about axis 2 with rotor momentum $h$ is stable when $(I_2 w + h - I_1 w)(I_2 w + h - I_3 w) > 0$:
here $h > (I_3 - I_2) w = 2$. `jd.critical_rotor_momenta` finds the critical momenta from the
linearisation, by root finding on its eigenvalues."""),
    ("code", r'''
inertia = jnp.array([1.0, 2.0, 3.0])
rate = 2.0
print("critical rotor momenta:", jd.critical_rotor_momenta(inertia, 1, rate))

J = 0.1  # rotor axial inertia
ts = jnp.linspace(0.0, 60.0, 601)
rotor = jd.Wheels(axes=[[0.0, 1.0, 0.0]], inertia=[J])
spinner = jd.Scene(jd.RigidBody(inertia), (rotor,))
fig, ax = plt.subplots(figsize=(9, 3.8))
for speed in (0.0, 10.0, 15.0, 25.0, 40.0):
    y0 = spinner.state(omega=[1e-3, rate, 1e-3], **{"wheels.speed": speed})
    traj = jd.simulate(spinner, y0, 60.0, ts=ts, rtol=1e-10, atol=1e-12)
    h = float(y0["wheels.momentum"][0])
    ax.plot(ts, traj.omega[:, 1], lw=1.3,
            label=f"rotor momentum h = {h:.1f}" + (" (stable)" if h > 2 else ""))
    if h > 2:
        assert float(jnp.min(traj.omega[:, 1])) > 1.99
ax.set(xlabel="time (s)", ylabel=r"$\omega_2$ (rad/s)",
       title="Spin about the intermediate axis: flips without enough rotor momentum")
ax.legend(fontsize=8, loc="lower left")
plt.show()'''),
    ("md", r"""
## 2. Reaction wheels detumble a spacecraft

Three orthogonal wheels and the rate-damping law `jd.RateDamping(k)`: the wheels apply the body
torque $-k\omega$, clipped to the motors' torque limit. The body's angular momentum moves into the
wheels: the total is conserved, and the wheels end up storing all of it."""),
    ("code", r'''
limit = 0.02
wheels = jd.Wheels(axes=jnp.eye(3), inertia=[0.05] * 3, motor=jd.RateDamping(0.5),
                   max_torque=[limit] * 3, max_speed=[600.0] * 3)
craft = jd.Scene(jd.RigidBody([10.0, 12.0, 15.0]), (wheels,), attitude=True)
ts = jnp.linspace(0.0, 600.0, 601)
traj = jd.simulate(craft, craft.state(omega=[0.05, -0.03, 0.04]), 600.0, ts=ts,
                   rtol=1e-10, atol=1e-12)
own = {k.split(".", 1)[1]: v for k, v in traj.ys.items() if k.startswith("wheels.")}
speeds = own["momentum"] / 0.05 - traj.omega @ wheels.axes.T
torques = jax.vmap(lambda t, y, o: wheels.motor_torque(t, y, o))(traj.ts, traj.ys, own)

fig, ax = plt.subplots(1, 3, figsize=(14, 3.8))
ax[0].semilogy(ts, jnp.linalg.norm(traj.omega, axis=1))
ax[0].set(xlabel="time (s)", ylabel=r"$|\omega|$ (rad/s)", title="Body rate")
for i in range(3):
    ax[1].plot(ts, speeds[:, i], label=f"wheel {i + 1}")
    ax[2].plot(ts, torques[:, i], label=f"wheel {i + 1}")
ax[1].set(xlabel="time (s)", ylabel="wheel speed (rad/s)", title="Wheels absorb the momentum")
ax[2].axhline(limit, color="0.5", ls=":", lw=1)
ax[2].axhline(-limit, color="0.5", ls=":", lw=1, label="torque limit")
ax[2].set(xlabel="time (s)", ylabel="motor torque (N m)", title="Motor torques, saturated early")
for a in ax[1:]:
    a.legend(fontsize=8)
plt.tight_layout()
plt.show()
h_n = traj.momentum_inertial
print("inertial momentum drift:", float(jnp.max(jnp.linalg.norm(h_n - h_n[0], axis=1))))
assert float(jnp.linalg.norm(traj.y_final["omega"])) < 1e-8
assert float(jnp.max(jnp.abs(torques))) <= limit + 1e-12'''),
    ("md", r"""
## 3. Pointing with reaction wheels

Quaternion feedback (`jd.AttitudeTracking`): body torque $-k_p\,\mathrm{sign}(\delta q_0)\,
\delta\boldsymbol q - k_d\,\omega$ with $\delta q = q_{\rm target}^* \otimes q$. The error angle
$2\,\mathrm{atan2}(|\delta\boldsymbol q|, |\delta q_0|)$ decays to zero."""),
    ("code", r'''
target = jd.quat_from_axis_angle(jnp.array([0.3, -0.2, 1.0]), 1.2)
pointing = jd.Wheels(axes=jnp.eye(3), inertia=[0.05] * 3,
                     motor=jd.AttitudeTracking(target, kp=0.5, kd=3.0), max_torque=[0.1] * 3)
craft = jd.Scene(jd.RigidBody([10.0, 12.0, 15.0]), (pointing,), attitude=True)
ts = jnp.linspace(0.0, 300.0, 301)
traj = jd.simulate(craft, craft.state(omega=[0.01, 0.0, -0.01]), 300.0, ts=ts,
                   rtol=1e-10, atol=1e-12)
dq = jax.vmap(lambda q: jd.quat_multiply(jd.quat_conjugate(target), q))(traj.quaternion)
# 2 atan2(|dq_vec|, |dq0|), not 2 arccos|dq0|: the latter reads round-off in |q| as an angle.
angle = 2 * jnp.arctan2(jnp.linalg.norm(dq[:, 1:], axis=1), jnp.abs(dq[:, 0]))
fig, ax = plt.subplots(figsize=(8, 3.5))
ax.semilogy(ts, jnp.degrees(angle))
ax.set(xlabel="time (s)", ylabel="pointing error (deg)", title="Slew to a target attitude")
plt.show()
assert float(angle[-1]) < 1e-9'''),
    ("md", r"""
## 4. The major-axis rule (Explorer 1)

A body spinning about its **minor** axis, with a viscous ring damper (a wheel without a motor,
coupled to the body by viscous friction $c$), dissipates energy at constant $|H|$. The least
energy compatible with $|H|$ is a spin about the axis of largest inertia: the spin wanders away
from the minor axis through the separatrix and settles about the major axis."""),
    ("code", r'''
damper = jd.Wheels(axes=[[1.0, 0.0, 1.0]], inertia=[0.05], damping=[0.02])
body = jd.Scene(jd.RigidBody(inertia), (damper,))
ts = jnp.linspace(0.0, 4000.0, 4001)
traj = jd.simulate(body, body.state(omega=[2.0, 0.05, 0.05]), 4000.0, ts=ts,
                   rtol=1e-10, atol=1e-12, max_steps=1_000_000)
h = traj.angular_momentum
cosines = jnp.abs(h) / jnp.linalg.norm(h, axis=1, keepdims=True)
energy = traj.energy
# The least energy for this |H|: rigid rotation of body and damper about their largest axis.
g = damper.axes[0]
i_max = np.linalg.eigvalsh(np.diag(inertia) + 0.05 * np.outer(g, g))[-1]

fig = plt.figure(figsize=(14, 4.2))
ax = fig.add_subplot(1, 3, 1)
ax.plot(ts, energy, color="C3")
ax.axhline(float(jnp.sum(h[0] ** 2)) / (2 * i_max), color="0.5", ls=":",
           label=r"$H^2 / 2 I_{\max}$")
ax.set(xlabel="time (s)", ylabel="kinetic energy (J)", title="Energy decays at constant |H|")
ax.legend()
ax = fig.add_subplot(1, 3, 2)
angles = np.degrees(np.arccos(np.clip(np.asarray(cosines), 0, 1)))
window = 40  # samples (s): envelopes of the fast nutation
blocks = angles[: len(angles) // window * window].reshape(-1, window, 3)
centres = np.asarray(ts)[: blocks.shape[0] * window].reshape(-1, window).mean(axis=1)
for i, name in enumerate(["minor", "intermediate", "major"]):
    ax.fill_between(centres, blocks[:, :, i].min(axis=1), blocks[:, :, i].max(axis=1),
                    color=f"C{i}", alpha=0.6, label=f"{name} axis")
ax.set(xlabel="time (s)", ylabel="angle between H and axis (deg)",
       title="From the minor to the major axis (nutation band)")
ax.legend(fontsize=8)
ax = fig.add_subplot(1, 3, 3, projection="3d")
u = np.asarray(h / jnp.linalg.norm(h, axis=1, keepdims=True))
p, q = np.mgrid[0 : 2 * np.pi : 40j, 0 : np.pi : 20j]
ax.plot_wireframe(np.cos(p) * np.sin(q), np.sin(p) * np.sin(q), np.cos(q), color="0.88", lw=0.4)
for arc in jd.separatrix_curves(inertia):
    ax.plot(arc[:, 0], arc[:, 1], arc[:, 2], color="crimson", lw=1.2)
for start, colour in ((0, "C0"), (2000, "C1"), (2500, "C2"), (3500, "C4")):
    seg = u[start : start + 40]
    ax.plot(seg[:, 0], seg[:, 1], seg[:, 2], color=colour, lw=2, label=f"t = {start} s")
ax.set(xlabel="$h_1$", ylabel="$h_2$", zlabel="$h_3$", title="Polhodes at four epochs")
ax.legend(fontsize=7, loc="upper left")
ax.set_box_aspect((1, 1, 1))
plt.tight_layout()
plt.show()
assert bool(jnp.all(jnp.diff(energy) < 0))
assert float(cosines[-1, 2]) > 0.999'''),
]


if __name__ == "__main__":
    build(SPIN, HERE / "07_spin_stabilisation.ipynb")
