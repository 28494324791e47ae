"""Build the example notebooks from the cell sources below (run: `python notebooks/_build.py`).

The notebooks are written without outputs; `tests/test_notebooks.py` executes them. Cell ids are
fixed, so rebuilding unchanged sources gives byte-identical files.
"""

from pathlib import Path

import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

HERE = Path(__file__).resolve().parent

X64 = '''\
# float64: the checks below compare against closed forms to ~1e-10.
jd.enable_compilation_cache()  # compiled programs are reused by the next kernel
jax.config.update("jax_enable_x64", True)'''

IMPORTS = '''\
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import jaxdyn as jd'''


# --------------------------------------------------------------------------------------------
# 01: the falling rod
# --------------------------------------------------------------------------------------------

ROD = [
    ("md", r"""
# The falling rod on frictionless ice"""),
    ("md", r"""
A slender rod stands almost upright on perfectly slippery ice and falls. Because the ice
can push only vertically, the rod's centre of mass drops straight down while the lower tip slides
out sideways. This notebook simulates the fall with `jaxdyn`, and checks it against the energy
integral, the quadrature for the fall time, and a scaling law for gradients taken through the
simulation."""),
    ("code", IMPORTS),
    ("code", X64),
    ("md", r"""
## The physics

The rod has length $L$, mass $m$ and moment of inertia $I_c = mL^2/12$ about its centre of mass
(CM); $\theta$ is its angle from the vertical. The only forces are gravity $-mg\,\hat{y}$ and the
normal force $N\hat{y}$ at the tip. With no horizontal force, the CM moves only vertically.
Three ingredients:

* the super-particle theorem, $\mathbf{F} = m\mathbf{a}_c$: $\;N - mg = m\ddot{y}_c$;
* $\dot{H}_c = L_c$ about the CM: $\;I_c\ddot\theta = N\,\tfrac{L}{2}\sin\theta$;
* the tip stays on the ice: $\;y_c = \tfrac{L}{2}\cos\theta$, so
  $\ddot{y}_c = -\tfrac{L}{2}(\ddot\theta\sin\theta + \dot\theta^2\cos\theta)$.

Eliminating $N$ and $\ddot{y}_c$ gives the equation of motion and the normal force:

$$\ddot\theta = \frac{3\sin\theta\,(2g - L\dot\theta^2\cos\theta)}{L\,(1 + 3\sin^2\theta)},
\qquad
N = mg - m\frac{L}{2}\left(\dot\theta^2\cos\theta + \ddot\theta\sin\theta\right).$$

The tip moves horizontally and $N$ is vertical, so $N$ does no work and the energy

$$E = \frac{mL^2}{24}\left(1 + 3\sin^2\theta\right)\dot\theta^2 + mg\frac{L}{2}\cos\theta$$

is conserved. From rest at $\theta_0$ it gives the rate as a function of the angle,
$\dot\theta^2 = 12g(\cos\theta_0 - \cos\theta)/\big(L(1 + 3\sin^2\theta)\big)$, and the fall time
as a quadrature, $T(\theta_0) = \int_{\theta_0}^{\pi/2} d\theta/\dot\theta$. Near upright,
$\ddot\theta \approx \lambda^2\theta$ with $\lambda = \sqrt{6g/L}$, so
$\theta \approx \theta_0\cosh\lambda t$: the rod needs a time of order
$\lambda^{-1}\ln(1/\theta_0)$ to get going, and $T$ grows without bound as $\theta_0 \to 0$, but
only logarithmically."""),
    ("md", r"""
## One fall

A 1 m, 1 kg rod starts at rest at $\theta_0 = 0.05$ rad (about 3°). The run ends at the event
`"flat"`, when the CM reaches the ice ($\theta = \pi/2$), located by root finding. Saved times
after the impact are `inf`: `traj.valid` masks them."""),
    ("code", r"""
rod = jd.FallingRod(length=1.0, mass=1.0, g=9.81)
scene = jd.Scene(rod)
tight = dict(rtol=1e-10, atol=1e-12)

theta0 = 0.05
t_end = 1.0
ts = jnp.linspace(0.0, t_end, 201)  # keep this length: a new length would recompile
traj = jd.simulate(scene, scene.state(theta=theta0), t_end, ts=ts, **tight)

valid = np.asarray(traj.valid)
t_impact = float(traj.t_final)
# Saved samples before the impact, then the final (impact) state itself.
t = np.append(np.asarray(traj.ts)[valid], t_impact)
theta = np.append(np.asarray(traj.theta)[valid], float(traj.y_final["theta"]))
theta_dot = np.append(np.asarray(traj.theta_dot)[valid], float(traj.y_final["theta_dot"]))

print(f"event 'flat' fired: {bool(traj.event['flat'])}")
print(f"impact time     T = {t_impact:.12f} s "
      f"(quadrature: {float(rod.fall_time(theta0)):.12f} s)")
print(f"impact rate       = {theta_dot[-1]:.10f} rad/s "
      f"(energy integral: {float(rod.rate(jnp.pi / 2, theta0)):.10f} rad/s)")
print(f"samples before impact: {valid.sum()} of {valid.size}")"""),
    ("md", r"""
Two independent checks: the simulated impact time against the quadrature
`rod.fall_time`, and the conservation of energy along the simulated samples."""),
    ("code", r"""
t_quad = float(rod.fall_time(theta0))
assert abs(t_impact - t_quad) / t_quad < 1e-8, (t_impact, t_quad)

energy = np.asarray(traj.energy)[valid]
energy_drift = np.max(np.abs(energy - energy[0])) / abs(energy[0])
assert energy_drift < 1e-8, energy_drift
print(f"impact time relative error {abs(t_impact - t_quad) / t_quad:.1e}, "
      f"energy drift {energy_drift:.1e}")"""),
    ("code", r"""
fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4), layout="constrained")
ax1.plot(t, np.degrees(theta), color="tab:blue")
ax1.axhline(90, color="gray", ls=":", lw=1)
ax1.set(xlabel="time $t$ (s)", ylabel=r"angle from vertical $\theta$ (deg)",
        title=r"Angle: a slow start, then a fast fall")
ax2.plot(t, theta_dot, color="tab:red")
ax2.set(xlabel="time $t$ (s)", ylabel=r"angular rate $\dot\theta$ (rad/s)",
        title=r"Angular rate")
for ax in (ax1, ax2):
    ax.axvline(t_impact, color="k", ls="--", lw=1, label=f"impact, $T$ = {t_impact:.4f} s")
    ax.set_xlim(0, 1.05 * t_impact)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left")
plt.show()"""),
    ("md", r"""
## Phase portrait against the energy integral

The energy integral gives $\dot\theta$ as a function of $\theta$ alone (`rod.rate`); the simulated
samples must lie on that curve."""),
    ("code", r"""
theta_grid = jnp.linspace(theta0, jnp.pi / 2, 400)
rate_curve = rod.rate(theta_grid, theta0)
rate_err = np.max(np.abs(theta_dot - np.asarray(rod.rate(theta, theta0))))
assert rate_err < 1e-8 * np.max(theta_dot), rate_err

fig, ax = plt.subplots(figsize=(7, 4.5), layout="constrained")
ax.plot(np.degrees(theta_grid), rate_curve, color="k", lw=1.5,
        label=r"energy integral $\dot\theta(\theta)$ (rod.rate)")
ax.plot(np.degrees(theta[::4]), theta_dot[::4], "o", ms=5, mfc="none", color="tab:red",
        label="simulation (every 4th sample)")
ax.set(xlabel=r"angle $\theta$ (deg)", ylabel=r"angular rate $\dot\theta$ (rad/s)",
       title=rf"Phase portrait from $\theta_0$ = {theta0} rad "
             rf"(largest deviation {rate_err:.0e} rad/s)")
ax.grid(alpha=0.3)
ax.legend(loc="upper left")
plt.show()"""),
    ("md", r"""
## The normal force

Near upright the CM barely accelerates and the ice carries the full weight. As the rod falls, the
CM accelerates downwards and $N$ drops well below $mg$; the minimum comes at about 62°, after which
$N$ rises again. At the impact, $\cos\theta = 0$ and
$\ddot\theta = 3g/(2L)$ whatever the rate, so $N = mg/4$ exactly. $N$ stays positive throughout,
so the tip never leaves the ice and the contact model holds for the whole fall."""),
    ("code", r"""
m, g = float(rod.mass), float(rod.g)
n_sim = np.asarray(traj.normal_force_over_weight)[valid]
n_curve = np.asarray(rod.normal_force_energy(theta_grid, theta0)) / (m * g)
i_min = int(np.argmin(n_curve))
theta_min, n_min = float(np.degrees(theta_grid[i_min])), float(n_curve[i_min])
assert np.all(n_sim > 0), "the tip would leave the ice"
assert abs(float(traj.final_outputs()["normal_force_over_weight"][0]) - 0.25) < 1e-9

fig, ax = plt.subplots(figsize=(7, 4.5), layout="constrained")
ax.plot(np.degrees(theta_grid), n_curve, color="k", lw=1.5, label="from the energy integral")
ax.plot(np.degrees(theta[:-1][::4]), n_sim[::4], "o", ms=5, mfc="none", color="tab:green",
        label="simulation (every 4th sample)")
ax.plot(theta_min, n_min, "v", color="tab:purple", ms=10,
        label=rf"minimum {n_min:.3f} at $\theta$ = {theta_min:.1f}°")
ax.axhline(0.25, color="gray", ls=":", lw=1, label="$mg/4$ at impact")
ax.set(xlabel=r"angle $\theta$ (deg)", ylabel=r"normal force $N/(mg)$",
       title="Normal force on the tip through the fall", ylim=(0, 1.05))
ax.grid(alpha=0.3)
ax.legend(loc="upper right")
plt.show()"""),
    ("md", r"""
## Fall time against the initial angle

`rod.fall_time` integrates the energy integral by Gauss-Legendre quadrature after a substitution
that removes the $\ln(1/\theta_0)$ growth from the integrand, so it stays accurate down to
$\theta_0 = 10^{-12}$; `jax.vmap` evaluates it over a whole grid at once. On a logarithmic
$\theta_0$ axis the curve becomes a straight line of slope $\lambda^{-1} = \sqrt{L/(6g)}$ per
e-fold. A few simulated impacts (same scene, same number of saved times, so no recompilation)
are overlaid."""),
    ("code", r"""
theta0_grid = jnp.logspace(-12, 0, 200)
fall_times = jax.jit(jax.vmap(rod.fall_time))(theta0_grid)
lam = np.sqrt(6 * g / float(rod.length))

# Small-angle law T = ln(1/theta0)/lam + c, with c matched at the smallest angle.
c = float(fall_times[0]) - np.log(1 / 1e-12) / lam
slope = float(fall_times[0] - fall_times[10]) / float(np.log(theta0_grid[10] / theta0_grid[0]))
assert abs(slope * lam - 1) < 1e-8, slope * lam

sim_theta0 = np.array([0.3, 1e-1, 1e-2, 1e-3, 1e-4, 1e-6, 1e-8])
sim_times = []
for th0 in sim_theta0:
    run = jd.simulate(scene, scene.state(theta=th0), 4.0, ts=jnp.linspace(0.0, 4.0, 201), **tight)
    assert bool(run.event["flat"])
    sim_times.append(float(run.t_final))
sim_times = np.array(sim_times)
quad_times = np.asarray(jax.vmap(rod.fall_time)(jnp.asarray(sim_theta0)))
assert np.max(np.abs(sim_times / quad_times - 1)) < 1e-6

fig, ax = plt.subplots(figsize=(7, 4.5), layout="constrained")
ax.semilogx(theta0_grid, fall_times, color="k", lw=1.5, label="quadrature (rod.fall_time)")
ax.semilogx(theta0_grid, np.log(1 / theta0_grid) / lam + c, color="tab:orange", ls="--",
            label=r"$\lambda^{-1}\ln(1/\theta_0) + c$, $\lambda = \sqrt{6g/L}$")
ax.semilogx(sim_theta0, sim_times, "o", ms=8, mfc="none", color="tab:red", mew=1.5,
            label="simulated impact")
ax.set(xlabel=r"initial angle $\theta_0$ (rad)", ylabel="fall time $T$ (s)",
       title=r"Fall time grows like $\ln(1/\theta_0)$", ylim=(0, None))
ax.grid(alpha=0.3, which="both")
ax.legend(loc="upper right")
plt.show()
print(f"slope dT/dln(1/theta0) = {slope:.10f} s, 1/lambda = {1 / lam:.10f} s")"""),
    ("md", r"""
## A gradient through the simulation

The impact time depends on the parameters only through the time scale $\sqrt{L/g}$ (the mass
cancels), so $T = \sqrt{L/g}\,f(\theta_0)$ and

$$\frac{\partial T}{\partial L} = \frac{T}{2L},\qquad
\frac{\partial T}{\partial g} = -\frac{T}{2g},\qquad \frac{\partial T}{\partial m} = 0.$$

`jax.grad` differentiates straight through `jd.simulate`, including the root finding that
locates the impact."""),
    ("code", r"""
def impact_time(params):
    s = scene.replace(**params)
    return jd.simulate(s, s.state(theta=theta0), t_end, **tight).t_final


T, grads = jax.value_and_grad(impact_time)(scene.parameters())
T = float(T)
laws = {"length": T / (2 * float(rod.length)), "g": -T / (2 * g), "mass": 0.0}
for name, law in laws.items():
    got = float(grads[name])
    print(f"dT/d{name:<6}  autodiff {got:+.10f}   scaling law {law:+.10f}")
    assert abs(got - law) < 1e-6 * abs(T), (name, got, law)"""),
]


# --------------------------------------------------------------------------------------------
# 02: torque-free motion
# --------------------------------------------------------------------------------------------

POLHODE = [
    ("md", r"""
# Torque-free motion: polhodes and the intermediate-axis flip"""),
    ("md", r"""
A rigid body spinning freely in space keeps its energy and the length of its angular
momentum, and these two constraints confine the body-frame angular momentum to closed curves, the
polhodes. This notebook draws them for a body with three different moments, follows the famous
flip of a body spun about its intermediate axis (the tennis-racket or Dzhanibekov effect),
compares the simulation with the Jacobi-elliptic closed form, and shows how the period of the
flip diverges as the motion approaches the separatrix."""),
    ("code", IMPORTS),
    ("code", X64),
    ("md", r"""
## Euler's equations and the polhodes

In the principal body frame, with $I = \mathrm{diag}(I_1, I_2, I_3)$ and no torque,

$$I\dot{\boldsymbol\omega} + \boldsymbol\omega \times I\boldsymbol\omega = 0 .$$

Dotting with $\boldsymbol\omega$ and with $I\boldsymbol\omega$ gives two invariants: the kinetic
energy $2T = \boldsymbol\omega\cdot I\boldsymbol\omega$ and $H^2 = |I\boldsymbol\omega|^2$ (the
vector $\mathbf{H}$ is fixed in inertial space; in the body frame only its length is). In terms of
the body-frame momentum $\mathbf{h} = I\boldsymbol\omega$,

$$h_1^2 + h_2^2 + h_3^2 = H^2 \quad\text{(momentum sphere)},\qquad
\frac{h_1^2}{I_1} + \frac{h_2^2}{I_2} + \frac{h_3^2}{I_3} = 2T \quad\text{(energy ellipsoid)},$$

and $\mathbf{h}$ moves along their intersection, the polhode. Multiplying the ellipsoid by $I_2$
and subtracting the sphere,

$$h_1^2\left(\frac{I_2}{I_1} - 1\right) + h_3^2\left(\frac{I_2}{I_3} - 1\right) = 2TI_2 - H^2 .$$

For $I_1 < I_2 < I_3$ the two coefficients have opposite signs. If $H^2 > 2TI_2$, $h_3$ can never
vanish and the polhode circles the major axis; if $H^2 < 2TI_2$, $h_1$ never vanishes and it
circles the minor axis. The separatrix $H^2 = 2TI_2$ is a pair of planes through the $h_2$ axis:
on the sphere, two great circles that cross at the saddles $\mathbf{h} = \pm H\hat{e}_2$, pure spin
about the intermediate axis.

Below, $I = (1, 2, 3)$ kg m² and $|\mathbf{h}| = 1$ N m s. The initial conditions lie on the
$h_1h_3$ meridian at an angle $\alpha$ from the $h_3$ axis; the separatrix crosses it where
$\tan^2\alpha = (1 - I_2/I_3)/(I_2/I_1 - 1)$, at $\alpha = 30°$. `jd.polhode` returns one period
of the closed-form rates; `jd.separatrix_condition` gives the sign of $H^2 - 2TI_2$."""),
    ("code", r"""
inertia = jnp.array([1.0, 2.0, 3.0])
alphas = np.radians([6.0, 14.0, 22.0, 27.0, 33.0, 42.0, 58.0, 76.0])
h0 = np.stack([np.sin(alphas), np.zeros_like(alphas), np.cos(alphas)], axis=1)
h0 = np.concatenate([h0, -h0])  # both ends of each axis
omega0s = jnp.asarray(h0) / inertia

polhodes = jax.jit(jax.vmap(lambda w: jd.polhode(inertia, w, num=300)))(omega0s)
h_curves = np.asarray(polhodes * inertia)  # h = I omega, shape (curves, points, 3)
about_major = np.asarray(jd.separatrix_condition(inertia, omega0s)) > 0
# Closed forms are jitted: compiled once, they cost far less than op-by-op evaluation.
separatrix = np.asarray(jax.jit(jd.separatrix_curves)(inertia, 1.0))  # (4 arcs, points, 3)

# Every polhode lies on the unit momentum sphere and on its own energy ellipsoid.
assert np.max(np.abs(np.linalg.norm(h_curves, axis=-1) - 1)) < 1e-10
two_t = np.sum(h_curves**2 / np.asarray(inertia), axis=-1)
assert np.max(np.abs(two_t - two_t[:, :1])) < 1e-10
# The separatrix arcs: on the sphere, and on the plane pair with 2 T I_2 = H^2.
i1, i2, i3 = np.asarray(inertia)
sep_cond = separatrix[..., 0] ** 2 * (i2 / i1 - 1) + separatrix[..., 2] ** 2 * (i2 / i3 - 1)
assert np.max(np.abs(sep_cond)) < 1e-12
assert np.max(np.abs(np.linalg.norm(separatrix, axis=-1) - 1)) < 1e-12
print(f"{about_major.sum()} polhodes circle the major axis, "
      f"{(~about_major).sum()} the minor axis")"""),
    ("code", r"""
elev, azim = 22, -58
view = np.array([np.cos(np.radians(elev)) * np.cos(np.radians(azim)),
                 np.cos(np.radians(elev)) * np.sin(np.radians(azim)), np.sin(np.radians(elev))])


def draw(ax, curve, label=None, **style):
    # Solid on the near side of the sphere, faint on the far side.
    near = (curve @ view >= 0)[:, None]
    ax.plot(*np.where(near, curve, np.nan).T, label=label, **style)
    ax.plot(*np.where(near, np.nan, curve).T, alpha=0.15, **style)


fig = plt.figure(figsize=(8, 7.5), layout="constrained")
ax = fig.add_subplot(projection="3d", proj_type="ortho")
u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 60), np.linspace(0, np.pi, 30))
ax.plot_surface(np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v),
                color="lightsteelblue", alpha=0.15, linewidth=0, shade=False)
# The outline of the sphere as seen from the viewpoint: the great circle normal to `view`.
e_a = np.cross(view, [0.0, 0.0, 1.0])
e_a /= np.linalg.norm(e_a)
e_b = np.cross(view, e_a)
psi = np.linspace(0, 2 * np.pi, 200)[:, None]
ax.plot(*(np.cos(psi) * e_a + np.sin(psi) * e_b).T, color="gray", lw=0.8)
colors = {True: "tab:blue", False: "tab:orange"}
labels = {True: "circles the major axis $h_3$", False: "circles the minor axis $h_1$"}
for curve, major in zip(h_curves, about_major):
    draw(ax, np.vstack([curve, curve[:1]]), label=labels.pop(major, None), color=colors[major],
         lw=1.5)
for k, arc in enumerate(separatrix):
    draw(ax, arc, label="separatrix $H^2 = 2TI_2$" if k == 0 else None, color="crimson", lw=3.5)
for y in (-1, 1):  # the saddles; the one on the far side faint
    ax.plot([0], [y], [0], "o", color="k", ms=7, alpha=1.0 if y * view[1] > 0 else 0.3,
            label=r"saddles $\pm H\hat{e}_2$" if y * view[1] > 0 else None)
ax.set(xlabel="$h_1$ (N m s)", ylabel="$h_2$ (N m s)", zlabel="$h_3$ (N m s)",
       xlim=(-1, 1), ylim=(-1, 1), zlim=(-1, 1),
       xticks=[-1, 0, 1], yticks=[-1, 0, 1], zticks=[-1, 0, 1])
ax.set_box_aspect((1, 1, 1))
ax.view_init(elev=elev, azim=azim)
ax.set_title("Polhodes on the momentum sphere $|\\mathbf{h}| = 1$, $I = (1, 2, 3)$ kg m²\n"
             "(far side of the sphere drawn faint)")
ax.legend(loc="upper left")
plt.show()"""),
    ("md", r"""
## The intermediate-axis flip

Spin the body almost exactly about its intermediate axis, $\boldsymbol\omega_0 = (\varepsilon,
\Omega, \varepsilon)$. Linearising Euler's equations about $(0, \Omega, 0)$ gives
$\delta\ddot\omega_1 = \sigma^2\,\delta\omega_1$ with

$$\sigma^2 = \Omega^2\,\frac{(I_2 - I_1)(I_3 - I_2)}{I_1 I_3} > 0 ,$$

so the small components grow like $e^{\sigma t}$ ($\sigma = 2/\sqrt{3} \approx 1.15$ s⁻¹ here), the
body turns over, $\omega_2 \to -\omega_2$, and comes back: the state creeps along the separatrix
from one saddle to the other. The closed form (Landau & Lifshitz, §37), for a polhode about the
major axis, is

$$\omega_1 = \pm A_1\,\mathrm{cn}(\lambda t + u_0 \mid m),\quad
\omega_2 = \pm A_2\,\mathrm{sn}(\lambda t + u_0 \mid m),\quad
\omega_3 = \pm A_3\,\mathrm{dn}(\lambda t + u_0 \mid m),$$

with period $4K(m)/\lambda$; `jd.torque_free_omega` evaluates it. We simulate 60 s from
$\boldsymbol\omega_0 = (10^{-3}, 2, 10^{-3})$ rad/s and overlay it."""),
    ("code", r"""
body = jd.RigidBody(inertia)
scene = jd.Scene(body)
omega0 = jnp.array([1e-3, 2.0, 1e-3])
t_end = 60.0
ts = jnp.linspace(0.0, t_end, 1201)  # keep this length for every run below: no recompilation
tight = dict(rtol=1e-10, atol=1e-12)
traj = jd.simulate(scene, scene.state(omega=omega0), t_end, ts=ts, **tight)

omega_exact = jax.jit(jd.torque_free_omega)
period_of = jax.jit(jd.torque_free_period)
t = np.asarray(traj.ts)
w_sim = np.asarray(traj.omega)
w_exact = np.asarray(omega_exact(inertia, omega0, ts))
err = np.max(np.abs(w_sim - w_exact), axis=-1)
assert err.max() < 1e-7, err.max()
period = float(period_of(inertia, omega0))
print(f"max |omega_sim - omega_closed_form| = {err.max():.1e} rad/s, period = {period:.6f} s")"""),
    ("code", r"""
fig, axes = plt.subplots(3, 1, figsize=(10, 6.5), sharex=True, layout="constrained")
names = [r"$\omega_1$ (minor)", r"$\omega_2$ (intermediate)", r"$\omega_3$ (major)"]
for k, ax in enumerate(axes):
    ax.plot(t, w_sim[:, k], color="tab:blue", lw=3, alpha=0.5, label="simulation")
    ax.plot(t, w_exact[:, k], color="k", lw=1, ls="--", label="closed form (Jacobi elliptic)")
    ax.axhline(0, color="gray", lw=0.5)
    ax.set_ylabel(names[k] + "\n(rad/s)")
    ax.grid(alpha=0.3)
axes[-1].set_xlabel("time $t$ (s)")
fig.suptitle(rf"Spin about the intermediate axis flips every {period / 2:.2f} s "
             r"($\omega_0 = (10^{-3}, 2, 10^{-3})$ rad/s)")
fig.legend(*axes[0].get_legend_handles_labels(), loc="outside lower center", ncols=2)
plt.show()"""),
    ("md", r"""
### The same motion seen from space

With `attitude=True` the scene also integrates the attitude quaternion (scalar first, body to
inertial), and `traj.momentum_inertial` rotates $\mathbf{h}$ into the inertial frame. In the body
the momentum components flip back and forth; in space the vector stays put, while the quaternion
shows the body tumbling end over end."""),
    ("code", r"""
scene_att = jd.Scene(body, attitude=True)
traj_att = jd.simulate(scene_att, scene_att.state(omega=omega0), t_end, ts=ts, **tight)
h_body = np.asarray(traj_att.angular_momentum)
h_inertial = np.asarray(traj_att.momentum_inertial)
quat = np.asarray(traj_att.quaternion)
h_scale = np.linalg.norm(h_inertial[0])
h_drift = np.max(np.linalg.norm(h_inertial - h_inertial[0], axis=-1)) / h_scale
assert h_drift < 1e-8, h_drift

fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5), layout="constrained")
for k in range(3):
    ax1.plot(t, h_body[:, k], color=f"C{k}", lw=1, ls="--", label=f"$h_{k + 1}$ body frame")
    ax1.plot(t, h_inertial[:, k], color=f"C{k}", lw=2.5, label=f"$H_{k + 1}$ inertial frame")
ax1.set(xlabel="time $t$ (s)", ylabel="angular momentum (N m s)",
        title=f"Momentum: flips in the body, fixed in space (drift {h_drift:.0e})")
ax1.legend(loc="upper center", bbox_to_anchor=(0.5, -0.15), ncols=3)
for k, name in enumerate(["$q_0$ (scalar)", "$q_1$", "$q_2$", "$q_3$"]):
    ax2.plot(t, quat[:, k], lw=1.2, label=name)
ax2.set(xlabel="time $t$ (s)", ylabel="quaternion component",
        title="Attitude quaternion: the body tumbles", ylim=(-1.1, 1.1))
ax2.legend(loc="upper center", bbox_to_anchor=(0.5, -0.15), ncols=4)
for ax in (ax1, ax2):
    ax.grid(alpha=0.3)
plt.show()"""),
    ("md", r"""
## The period diverges at the separatrix

The body spends most of each period creeping past the two saddles. Starting a distance
$\sim\varepsilon$ from a saddle, it takes $\sigma^{-1}\ln(1/\varepsilon)$ to arrive and as long to
leave, and there are two saddles per period, so

$$P \approx \frac{4}{\sigma}\ln\frac{1}{\varepsilon} + \text{const}:$$

a logarithmic divergence, a straight line on a logarithmic $\varepsilon$ axis. In the closed form,
$P = 4K(m)/\lambda$ with $K(m) \approx \tfrac12\ln\big(16/(1 - m)\big)$ as $m \to 1$, and
$1 - m \propto \varepsilon^2$ (`jd.elliptic_parameter` returns $1 - m$ without cancellation).
Simulated periods, measured from the zero crossings of $\omega_2$, are overlaid. (Closer to the
separatrix the simulated period becomes ill-conditioned: it depends on
$H^2 - 2TI_2 \propto \varepsilon^2$, a tiny difference of two invariants that the integrator
conserves only to its tolerance.)"""),
    ("code", r"""
def omega_eps(eps):
    return jnp.stack([eps, 2.0, eps])


eps_grid = jnp.logspace(-1, -8, 120)
periods, one_minus_m = jax.jit(jax.vmap(
    lambda e: (jd.torque_free_period(inertia, omega_eps(e)),
               jd.elliptic_parameter(inertia, omega_eps(e))[1])))(eps_grid)
sigma = 2.0 * np.sqrt((i2 - i1) * (i3 - i2) / (i1 * i3))
slope = float(periods[-1] - periods[-11]) / float(np.log(eps_grid[-11] / eps_grid[-1]))
assert abs(slope * sigma / 4 - 1) < 1e-4, slope * sigma / 4
c = float(periods[-1]) - 4 / sigma * np.log(1 / float(eps_grid[-1]))


def flip_period(t, w2):
    # Zero crossings of omega_2, linearly interpolated; every other one is a full period apart.
    i = np.nonzero(np.sign(w2[:-1]) != np.sign(w2[1:]))[0]
    tc = t[i] - w2[i] * (t[i + 1] - t[i]) / (w2[i + 1] - w2[i])
    return tc[2] - tc[0]


sim_eps = np.array([1e-1, 1e-2, 1e-3, 1e-4, 1e-5])
sim_periods = []
for e in sim_eps:
    w0 = omega_eps(e)
    t1 = 1.6 * float(period_of(inertia, w0))  # long enough for three crossings
    run = jd.simulate(scene, scene.state(omega=w0), t1, ts=jnp.linspace(0.0, t1, ts.size), **tight)
    sim_periods.append(flip_period(np.asarray(run.ts), np.asarray(run.omega)[:, 1]))
sim_periods = np.array(sim_periods)
closed_periods = np.array([float(period_of(inertia, omega_eps(e))) for e in sim_eps])
assert np.max(np.abs(sim_periods / closed_periods - 1)) < 1e-5

fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5), layout="constrained")
ax1.semilogx(eps_grid, periods, color="k", lw=1.5, label="closed form $4K(m)/\\lambda$")
ax1.semilogx(eps_grid, 4 / sigma * np.log(1 / eps_grid) + c, color="tab:orange", ls="--",
             label=r"$(4/\sigma)\ln(1/\varepsilon)$ + const")
ax1.semilogx(sim_eps, sim_periods, "o", ms=8, mfc="none", mew=1.5, color="tab:red",
             label=r"simulation (zero crossings of $\omega_2$)")
ax1.invert_xaxis()
ax1.set(xlabel=r"perturbation $\varepsilon$ (rad/s), $\omega_0 = (\varepsilon, 2, \varepsilon)$",
        ylabel="period $P$ (s)", title="Period of the flip: logarithmic divergence")
ax1.legend(loc="upper left")
ax2.loglog(eps_grid, one_minus_m, color="k", lw=1.5, label="$1 - m$ (jd.elliptic_parameter)")
ax2.loglog(eps_grid, float(one_minus_m[0] / eps_grid[0] ** 2) * eps_grid**2, color="tab:orange",
           ls="--", label=r"$\propto \varepsilon^2$")
ax2.invert_xaxis()
ax2.set(xlabel=r"perturbation $\varepsilon$ (rad/s)", ylabel="$1 - m$",
        title="Distance to the separatrix")
ax2.legend(loc="upper right")
for ax in (ax1, ax2):
    ax.grid(alpha=0.3, which="major")
plt.show()
print(f"slope dP/dln(1/eps) = {slope:.6f} s, 4/sigma = {4 / sigma:.6f} s")"""),
    ("md", r"""
## Conservation and accuracy

Over the 60 s run, the relative drift of the energy, of $|\mathbf{H}|$ and of the inertial
momentum vector, and the distance to the closed form. The error against the closed form rises and
falls with the flips: leaving a saddle, the small components and their errors grow like
$e^{\sigma t}$; approaching the next saddle, they shrink like $e^{-\sigma t}$."""),
    ("code", r"""
def rel_drift(x):
    x = np.asarray(x)
    d = np.abs(x / x[0] - 1)
    return np.where(d > 0, d, np.nan)  # exact zeros have no place on a log axis


drifts = {
    "energy $T$": rel_drift(traj_att.energy),
    r"$|\mathbf{H}|$": rel_drift(traj_att.momentum),
    r"inertial $\mathbf{H}$ (vector)": np.where(
        t > 0, np.linalg.norm(h_inertial - h_inertial[0], axis=-1)
        / np.linalg.norm(h_inertial[0]), np.nan),
}
for name, d in drifts.items():
    assert np.nanmax(d) < 1e-8, (name, np.nanmax(d))

fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5), layout="constrained")
for name, d in drifts.items():
    ax1.semilogy(t, d, lw=1.2, label=name)
ax1.set(xlabel="time $t$ (s)", ylabel="relative drift",
        title=r"Conserved quantities (rtol = $10^{-10}$)")
ax1.legend(loc="lower right")
ax2.semilogy(t, np.where(err > 0, err, np.nan), color="tab:purple", lw=1.2,
             label=r"$\max_k |\omega_k - \omega_k^{\rm closed}|$")
ax2.axhline(1e-7, color="gray", ls=":", label="tolerance of the check")
flips = t[np.nonzero(np.sign(w_sim[:-1, 1]) != np.sign(w_sim[1:, 1]))[0]]
for k, t_flip in enumerate(flips):
    ax2.axvline(t_flip, color="k", lw=0.5, ls="--",
                label="flips ($\\omega_2 = 0$)" if k == 0 else None)
ax2.set(xlabel="time $t$ (s)", ylabel="error (rad/s)",
        title="Simulation against the closed form")
ax2.legend(loc="lower right")
for ax in (ax1, ax2):
    ax.grid(alpha=0.3, which="major")
plt.show()"""),
]


def build(cells, path):
    nb = new_notebook()
    nb.metadata["kernelspec"] = {
        "name": "python3", "display_name": "Python 3", "language": "python",
    }
    nb.metadata["language_info"] = {"name": "python"}
    for k, (kind, source) in enumerate(cells):
        source = source.strip("\n")
        cell = new_markdown_cell(source) if kind == "md" else new_code_cell(source)
        cell.id = f"cell-{k:02d}"
        nb.cells.append(cell)
    nbformat.validate(nb)
    nbformat.write(nb, path)


if __name__ == "__main__":
    build(ROD, HERE / "01_falling_rod.ipynb")
    build(POLHODE, HERE / "02_torque_free_polhode.ipynb")
