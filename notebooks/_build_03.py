"""Build notebook 03 (run: `python notebooks/_build_03.py`); see `_build.py`."""

from _build import HERE, IMPORTS, X64, build

IDENTIFY = [
    ("md", r"""
# Identifying a tumbling body's inertia from noisy rate measurements"""),
    ("md", r"""
A gyro on a tumbling body records its angular velocity in the body frame. How much does that
record tell us about the body? This notebook fits the full inertia tensor (principal moments and
principal axes) and the initial rates to noisy samples with `jd.fit`, which integrates the
scene with diffrax and differentiates through the integrator. It shows why only the *shape* of
the tensor can be found from a torque-free record, how the fit converges, the fitted and true
inertia ellipsoids, and how honest the 1-sigma intervals are over many noise draws."""),
    ("code", IMPORTS),
    ("code", X64 .replace(
        "# float64: the checks below compare against closed forms to ~1e-10.",
        "# float64: the fit differentiates through the integrator; its Jacobians and the\n"
        "# Gauss-Newton intervals need the precision (the command line enables it too).")),
    ("md", r"""
## What the rates can tell

Euler's equations of the torque-free body, $I\dot\omega + \omega\times I\omega = 0$, are
unchanged when $I$ is multiplied by any constant: the rates determine the inertia tensor only up
to a common factor. `jd.fit` finds this by itself (the Jacobian column of the scale is zero),
keeps the scale fixed, and reports the moments normalised so that the largest is 1. A known
torque, or a rotor of known momentum, would fix the scale.

Every iterate of the fit must be a physical body: positive moments obeying the triangle
inequality $I_i \le I_j + I_k$. `jd.ValidInertia` guarantees it by construction: with
$x, y, z > 0$ (a scale times a softmax of two numbers), $(I_1, I_2, I_3) = (y + z,\, x + z,\,
x + y)$, and the principal axes are a rotation matrix of three modified Rodrigues parameters.
Six unconstrained numbers, no constraint anywhere."""),
    ("md", r"""
## The data

A body with principal moments in the ratio $0.45 : 0.70 : 1$ and principal axes turned
away from the body frame, tumbling at about 1 rad/s. The rates come from the closed-form
Jacobi-elliptic solution (`exact_omega`), an independent route from the integrator used by the
fit; 150 samples over 15 s, with gyro noise of 0.01 rad/s."""),
    ("code", r'''
moments_true = 2.4 * jnp.array([0.45, 0.70, 1.0])
axes_true = jd.quat_to_dcm(jd.quat_from_axis_angle(jnp.array([1.0, 2.0, 0.5]), 0.9))
tensor_true = jd.inertia_tensor(moments_true, axes_true)
omega0_true = jnp.array([0.5, -0.7, 0.6])

ts = jnp.linspace(0.0, 15.0, 150)
clean = jd.RigidBody(tensor_true).exact_omega(omega0_true, ts)
noise = 0.01
data = clean + noise * jax.random.normal(jax.random.PRNGKey(3), clean.shape)
print(f"{ts.size} samples, rates up to {float(jnp.max(jnp.abs(clean))):.2f} rad/s, "
      f"noise {noise} rad/s")'''),
    ("md", r"""
## The fit

The scene starts from a guess, a body of moments $0.6 : 0.8 : 1$ aligned with the body frame
(given as a full tensor, so that later fits that start elsewhere reuse the compilation). We fit
the inertia through `jd.ValidInertia()` and the initial rates (starting from the first
sample). The minimiser is Levenberg-Marquardt from optimistix, with exact Jacobians from
forward-mode differentiation through the diffrax solve (a handful of unknowns: a forward pass
carrying all tangents costs about one reverse pass and needs no checkpointing). Each start is
fitted to the first 25 %, then 50 %, then all of the record (a short record has few local
minima); starts are drawn at random until two agree."""),
    ("code", r'''
scene = jd.Scene(jd.RigidBody(jnp.diag(jnp.array([0.6, 0.8, 1.0]))))
res = jd.fit(scene, ts, {"omega": data}, parameters={"inertia": jd.ValidInertia()},
             initial=["omega"], key=0)

moments = np.asarray(res.values["inertia.principal_moments"])
std = np.asarray(res.std["inertia.principal_moments"])
truth, axes_ref = (np.asarray(a) for a in jd.principal_axes(tensor_true))
truth = truth / truth[-1]
axes = np.asarray(res.values["inertia.principal_axes"])
# 1-sigma of each axis direction (radians), from the intervals of its components.
axes_sigma = np.linalg.norm(np.asarray(res.std["inertia.principal_axes"]), axis=0)
for note in res.notes:
    print("note:", note)
print(f"converged: {res.converged} after {res.iterations} iterations; "
      f"final losses of the starts: {np.array2string(res.restart_losses, precision=4)}")
print(f"residual RMS {res.residual_rms:.4f} rad/s (noise {noise})")
angles = np.arccos(np.minimum(1.0, np.abs(np.sum(axes * axes_ref, axis=0))))
for i in range(3):
    print(f"I{i + 1}/I3 = {moments[i]:.4f} +- {std[i]:.4f}   (true {truth[i]:.4f}); "
          f"axis {i + 1} off by {np.degrees(angles[i]):.2f} deg "
          f"(1-sigma {np.degrees(axes_sigma[i]):.2f} deg)")

assert res.converged and not res.identifiable["inertia.scale"]
assert np.all(np.abs(moments - truth) <= 4 * std + 1e-12), (moments, truth, std)
assert np.all(angles <= 4 * axes_sigma) and np.all(np.sum(axes * axes_ref, axis=0) > 0)
assert abs(res.residual_rms - noise) < 0.2 * noise'''),
    ("md", r"""
## Convergence

The loss $\tfrac12\sum_k |\omega(t_k) - d_k|^2$ of the best start at each iteration. It jumps
up where the fit moves on to a longer part of the record (more samples count), then falls to
the noise floor: $\tfrac12 N \cdot 3\sigma^2$ for $N$ samples of three rates with noise
$\sigma$."""),
    ("code", r'''
fig, ax = plt.subplots(figsize=(8, 4.2), layout="constrained")
ax.semilogy(np.arange(res.history.size), res.history, "o-", ms=3, color="tab:blue",
            label="loss of the best start")
for k, start in enumerate(res.stages):
    ax.axvline(start, color="gray", ls=":", lw=1)
    ax.text(start + 0.4, 1.5 * res.history.min(),
            ["fit to the first 25 %", "first 50 %", "all samples"][k], va="bottom",
            fontsize=9, color="dimgray")
floor = 0.5 * ts.size * 3 * noise**2
ax.axhline(floor, color="tab:red", ls="--", lw=1,
           label=r"noise floor $\frac{1}{2}N\cdot 3\sigma^2$")
ax.set(xlabel="iteration (Levenberg-Marquardt)", ylabel="loss",
       title="Convergence of the fit, over a growing part of the record")
ax.grid(alpha=0.3, which="both")
ax.legend(loc="upper right", bbox_to_anchor=(1.0, 0.85))
plt.show()

for a, b in zip((*res.stages, res.history.size), (*res.stages[1:], res.history.size)):
    stage = res.history[a:b]
    assert np.all(np.diff(stage) <= 1e-12 * stage[0])  # never worse within a stage
assert abs(res.history[-1] / floor - 1) < 0.2'''),
    ("md", r"""
## Data and fitted model

The fitted scene and initial state (`res.scene`, `res.y0`) integrate back to the record."""),
    ("code", r'''
fine = jnp.linspace(0.0, 15.0, 600)
fitted = jd.simulate(res.scene, res.y0, fine[-1], ts=fine, rtol=1e-10, atol=1e-12)
fig, ax = plt.subplots(figsize=(10, 4), layout="constrained")
for i, c in enumerate(["tab:blue", "tab:orange", "tab:green"]):
    ax.plot(ts, data[:, i], ".", ms=4, color=c, alpha=0.6)
    ax.plot(fine, fitted.omega[:, i], color=c, lw=1.2, label=rf"$\omega_{i + 1}$ fitted")
ax.set(xlabel="time $t$ (s)", ylabel="body rate (rad/s)",
       title="Noisy gyro samples (dots) and the fitted model (lines)")
ax.legend(loc="upper right", ncol=3)
ax.grid(alpha=0.3)
plt.show()'''),
    ("md", r"""
## Inertia ellipsoids

The inertia ellipsoid $\{x : x^T I x = 1\}$ has semi-axes $1/\sqrt{I_i}$ along the principal
axes. The fitted (normalised) tensor against the true one, scaled alike, and the starting
guess."""),
    ("code", r'''
def ellipsoid(tensor, n=24):
    m, a = np.linalg.eigh(np.asarray(tensor))
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, n), np.linspace(0, np.pi, n // 2))
    sphere = np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)])
    pts = np.einsum("ij,jkl->ikl", a / np.sqrt(m), sphere)
    return pts, a / np.sqrt(m)


tensor_fit = jd.inertia_tensor(jnp.asarray(moments), jnp.asarray(axes))
fig = plt.figure(figsize=(11, 5.2), layout="constrained")
views = [(20, 35), (60, 120)]
for k, (elev, azim) in enumerate(views):
    ax = fig.add_subplot(1, 2, k + 1, projection="3d")
    guess, _ = ellipsoid(jnp.diag(jnp.array([0.6, 0.8, 1.0])))
    ax.plot_wireframe(*guess, color="tab:blue", lw=0.5, alpha=0.45, label="starting guess")
    true_pts, true_axes = ellipsoid(tensor_true / moments_true[-1])
    ax.plot_wireframe(*true_pts, color="k", lw=0.6, alpha=0.8, label="true")
    fit_pts, fit_axes = ellipsoid(tensor_fit)
    ax.plot_surface(*fit_pts, color="tab:orange", alpha=0.35, lw=0, label="fitted")
    for i in range(3):
        for s in (-1, 1):
            ax.plot(*np.stack([np.zeros(3), s * fit_axes[:, i]], axis=1), color="tab:red",
                    lw=1.5)
    ax.set(xlabel="$x_B$", ylabel="$y_B$", zlabel="$z_B$", xlim=(-1.4, 1.4),
           ylim=(-1.4, 1.4), zlim=(-1.4, 1.4))
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev, azim)
    if k == 0:
        ax.legend(loc="upper left")
fig.suptitle("Inertia ellipsoids in the body frame: true (black), fitted (orange, red axes), "
             "starting guess (blue)")
plt.show()
assert np.allclose(np.asarray(tensor_fit), np.asarray(tensor_true) / float(moments_true[-1]),
                   atol=0.01)'''),
    ("md", r"""
## How honest are the intervals?

The 1-sigma intervals come from the Gauss-Newton approximation: the residual variance times
$(J^T J)^{-1}$ at the optimum, propagated to the principal moments through the Jacobian of the
map from the unconstrained numbers. Over repeated noise draws, about 68 % of the intervals
should contain the truth. Here 30 more records of the same body, each with fresh noise, each
fitted from the truth over the whole record at once (the same compiled fit: only the data
and the starting values change)."""),
    ("code", r'''
draws = 30
fits = []
for seed in range(draws):
    d = clean + noise * jax.random.normal(jax.random.PRNGKey(100 + seed), clean.shape)
    r = jd.fit(scene.replace(inertia=tensor_true), ts, {"omega": d},
               parameters={"inertia": jd.ValidInertia()}, initial=["omega"], restarts=1,
               horizons=(1.0,))
    fits.append((np.asarray(r.values["inertia.principal_moments"])[:2],
                 np.asarray(r.std["inertia.principal_moments"])[:2]))
m_draws = np.array([f[0] for f in fits])
s_draws = np.array([f[1] for f in fits])
covered = np.abs(m_draws - truth[:2]) <= s_draws
print(f"intervals covering the truth: {covered.sum()} of {covered.size} "
      f"({covered.mean():.0%}; expected 68 %)")

fig, axs = plt.subplots(1, 2, figsize=(11, 4.2), layout="constrained")
for i, ax in enumerate(axs):
    colors = np.where(covered[:, i], "tab:blue", "tab:red")
    for k in range(draws):
        ax.errorbar(k, m_draws[k, i], yerr=s_draws[k, i], fmt="o", ms=3, capsize=2,
                    color=colors[k])
    ax.axhline(truth[i], color="k", lw=1, label="truth")
    ax.errorbar(-2, moments[i], yerr=std[i], fmt="s", ms=5, capsize=3, color="tab:green",
                label="the fit above")
    ax.set(xlabel="noise draw", ylabel=rf"$I_{i + 1}/I_3$",
           title=rf"$I_{i + 1}/I_3$: {covered[:, i].sum()} of {draws} intervals cover "
                 "the truth")
    ax.grid(alpha=0.3)
    low, high = ax.get_ylim()
    ax.set_ylim(low, high + 0.3 * (high - low))  # room for the legend
    ax.legend(loc="upper right", ncol=2)
plt.show()

# 60 intervals (two per draw, correlated): expect about 41; allow a wide binomial margin.
assert 28 <= covered.sum() <= 54, covered.sum()
assert np.all(np.abs(m_draws - truth[:2]) <= 5 * s_draws)'''),
    ("md", r"""
## From the command line

The same fit reads a CSV file: `jaxdyn fit rates.csv --scene torque-free --json` (columns
`t,wx,wy,wz`, optionally `q0..q3` for the attitude) prints the normalised principal moments,
the axes, their intervals and what could not be identified. For the falling rod
(`t,theta`, `--scene falling-rod`, `--set g=...`), the angle determines the length, and the fit
reports that the mass cannot be found: it cancels from the rod's equation of motion."""),
]


if __name__ == "__main__":
    build(IDENTIFY, HERE / "03_identification.ipynb")
