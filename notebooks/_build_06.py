"""Build notebook 06 (run: `python notebooks/_build_06.py`); see `_build.py`."""

from _build import HERE, IMPORTS, build

MONTE_CARLO = [
    ("md", r"""
# Monte Carlo ensembles: flip times, nutation cones and fall times under uncertainty"""),
    ("md", r"""
A single simulation answers "what happens to *this* body"; an engineer usually needs "what
happens to every body that could have come off the line, launched with every rate the sensors
cannot rule out". `jd.ensemble` runs thousands of trajectories of one scene in one compiled batch,
each with its own draw of parameters and initial values, reduces each run to a few numbers with an
`observe` function, and keeps only those. This notebook asks three such questions: how long a
spin about the intermediate axis lasts before it flips, how likely spins about the major and
minor axes are to stay inside a given cone, and how long a rod balanced on ice stays up. Each
answer is checked against a closed form computed without the integrator."""),
    ("code", IMPORTS),
    ("code", r"""
# float64: flip times are compared with the closed-form period to ~1e-3 s after dozens of seconds
# of exponential growth of 1e-3 rad/s perturbations, which float32 could not resolve.
jd.enable_compilation_cache()  # compiled programs are reused by the next kernel
jax.config.update("jax_enable_x64", True)"""),
    ("md", r"""
## How an ensemble is described

`jd.ensemble(scene, y0, t1, n=..., vary={...}, observe=...)` simulates `n` trajectories from the
state `y0`. Trajectory `i` draws the values named in `vary` from `jax.random.fold_in(key, i)`:
parameters of the scene (`"inertia"`) or initial values (`"omega"`, or one component,
`"omega[0]"`), from `jd.Normal(mean, std)`, `jd.Uniform(low, high)`,
`jd.LogNormal(median, sigma)` (that is $\text{median}\cdot e^{\sigma Z}$, a relative spread of
about $\sigma$) or `jd.Fixed(value)`. `observe` maps one `jd.Trajectory` to a dict of small arrays;
it is traced once and applied to every run inside the compiled batch, so it is written with
`jax.numpy`. Only the distributions' numbers are arguments of the compiled batch: the runs below
that change a mean or a spread but not the names, the observation or the save times reuse one
compilation."""),
    ("md", r"""
## 1. Intermediate-axis flip times

A body spun about its intermediate axis, $\boldsymbol\omega_0 = (\varepsilon_1, w,
\varepsilon_3)$, keeps spinning for a while and then flips: $\omega_2$ reverses, and reverses
again half a period later (notebook 02). Linearising Euler's equations about the pure spin gives

$$\dot\omega_1 = -\frac{I_3 - I_2}{I_1}\,w\,\omega_3, \qquad
\dot\omega_3 = -\frac{I_2 - I_1}{I_3}\,w\,\omega_1,$$

whose growing mode $e^{\lambda t}$ has

$$\lambda = w\sqrt{\frac{(I_2 - I_1)(I_3 - I_2)}{I_1 I_3}}, \qquad
\omega_3 = -\kappa\,\omega_1 \text{ along it}, \quad
\kappa = \sqrt{\frac{(I_2 - I_1)\,I_1}{(I_3 - I_2)\,I_3}}.$$

The initial rates excite it with amplitude $a = (\varepsilon_1 - \varepsilon_3/\kappa)/2$ (in
$\omega_1$). The flip itself follows the separatrix, on which $\omega_2 = -w\tanh\lambda(t -
t_f)$ and $\omega_1 = A\,\mathrm{sech}\,\lambda(t - t_f)$ with $A = w\sqrt{I_2(I_3 - I_2)/(I_1(I_3
- I_1))}$. Matching the growing exponential $a e^{\lambda t}$ to the separatrix's tail $2A
e^{\lambda(t - t_f)}$ gives the time of the first flip, $\omega_2 = 0$:

$$t_f = \frac{1}{\lambda}\ln\frac{2A}{|a|} .$$

The flip time depends on the perturbation only logarithmically: a thousand times smaller
perturbation buys a fixed extra $\ln(1000)/\lambda$ seconds, and a Gaussian perturbation gives a
skewed distribution with a long tail of late flips (the draws with $|a|$ close to zero)."""),
    ("md", r"""
### First, a warning about the nominal body

The body of notebooks 02 and 04, $I = (1, 2, 3)$ kg m², is a flat plate: $I_3 = I_1 + I_2$
exactly, the edge of the triangle inequality that every real body satisfies. Perturbing each
moment by 1% makes about half of the draws impossible bodies. The ensemble does not stop: it marks
those runs `invalid_input`, keeps the others, and says why."""),
    ("code", r"""
w = 1.0  # spin rate about the intermediate axis (rad/s)
body = jd.Scene(jd.RigidBody(inertia=[1.0, 2.0, 3.0]))
t_flip_end = 80.0
ts_flip = jnp.linspace(0.0, t_flip_end, 801)


def flip_times(traj):
    # The first two sign changes of omega_2, linearly interpolated between saved samples.
    t, w2 = traj.ts, traj.ys["omega"][:, 1]
    change = traj.valid[:-1] & traj.valid[1:] & (jnp.sign(w2[:-1]) != jnp.sign(w2[1:]))
    t_cross = jnp.where(change, t[:-1] + w2[:-1] / (w2[:-1] - w2[1:]) * (t[1:] - t[:-1]),
                        jnp.inf)
    first = jnp.min(t_cross)
    second = jnp.min(jnp.where(t_cross > first, t_cross, jnp.inf))
    return {"flip_1": first, "flip_2": second, "omega0": traj.ys["omega"][0],
            "inertia": traj.scene.parameters()["inertia"]}


def flip_ensemble(inertia, inertia_spread, rate_mean, rate_spread, key):
    return jd.ensemble(
        body, body.state(omega=[0.0, w, 0.0]), t_flip_end, n=2000, key=key, ts=ts_flip,
        vary={"inertia": jd.LogNormal(inertia, inertia_spread),
              "omega[0]": jd.Normal(rate_mean, rate_spread),
              "omega[2]": jd.Normal(0.0, rate_spread)},
        observe=flip_times)


plate = flip_ensemble([1.0, 2.0, 3.0], 0.01, 0.0, 1e-3, key=0)
print(plate.status_counts())
print(plate.failures(1)[0]["message"])
assert 0.4 < plate.failed / plate.n < 0.6"""),
    ("md", r"""
So the body here is a thicker one, $I = (1, 2, 2.7)$ kg m², a safe 10% inside the triangle
inequality. Three ensembles of 2000 runs separate the two sources of uncertainty:

* **rates only**: nominal inertia, $\varepsilon_1, \varepsilon_3 \sim \mathcal{N}(0, (10^{-3}
  w)^2)$;
* **inertia only**: each moment with a 1% log-normal spread, fixed $\varepsilon_1 = 10^{-3}w$,
  $\varepsilon_3 = 0$;
* **both**.

A spread of zero makes a distribution a constant of the same kind, so the three share one
compilation."""),
    ("code", r"""
inertia = np.array([1.0, 2.0, 2.7])
runs = {
    "rates only": flip_ensemble(inertia, 0.0, 0.0, 1e-3, key=1),
    "inertia only": flip_ensemble(inertia, 0.01, 1e-3, 0.0, key=2),
    "both": flip_ensemble(inertia, 0.01, 0.0, 1e-3, key=3),
}
for name, res in runs.items():
    t1 = res.values["flip_1"][res.ok]
    print(f"{name:>12}: {res.completed}/{res.n} ok, first flip at {np.mean(t1):5.2f} s "
          f"(std {np.std(t1):.2f} s, 5-95% range {np.percentile(t1, 5):.2f}-"
          f"{np.percentile(t1, 95):.2f} s), {res.timing['trajectories_per_s']:.0f} runs/s")
    assert res.failed == 0 and np.all(np.isfinite(res.values["flip_2"]))"""),
    ("md", r"""
Two checks by independent routes, per run:

* the time between the first and second flip is half the period of the rates, which
  `jd.torque_free_period` computes from the complete elliptic integral $4K(m)/\lambda'$ for the
  sampled inertia and initial rates, without integrating;
* the first flip time agrees with the matched-asymptotics formula $t_f = \lambda^{-1}\ln(2A/|a|)$
  above, evaluated with each run's own inertia and rates."""),
    ("code", r"""
def linear_prediction(inertia, omega0):
    i1, i2, i3 = inertia.T
    w1, w2, w3 = omega0.T
    lam = np.abs(w2) * np.sqrt((i2 - i1) * (i3 - i2) / (i1 * i3))
    kappa = np.sqrt((i2 - i1) * i1 / ((i3 - i2) * i3))
    amp = np.abs(w2) * np.sqrt(i2 * (i3 - i2) / (i1 * (i3 - i1)))
    a = (w1 - w3 / kappa) / 2
    return np.log(2 * amp / np.abs(a)) / lam, np.abs(a), lam, amp


period = jax.jit(jax.vmap(jd.torque_free_period))
for name, res in runs.items():
    v = res.values
    half = np.asarray(period(v["inertia"], v["omega0"])) / 2
    err_half = np.max(np.abs(v["flip_2"] - v["flip_1"] - half))
    err_lin = np.max(np.abs(v["flip_1"] - linear_prediction(v["inertia"], v["omega0"])[0]))
    print(f"{name:>12}: max |(t2 - t1) - P/2| = {err_half:.1e} s, "
          f"max |t1 - t_f| = {err_lin:.1e} s")
    assert err_half < 1e-3 and err_lin < 1e-3, (name, err_half, err_lin)"""),
    ("md", r"""
With the inertia fixed, the flip time is a function of $|a|$ alone, and $a$ is Gaussian with
standard deviation $\sigma_a = \tfrac12\sigma\sqrt{1 + \kappa^{-2}}$. So
$P(t_f > \tau) = P(|a| < 2Ae^{-\lambda\tau}) = \mathrm{erf}(u)$ with
$u = 2Ae^{-\lambda\tau}/(\sqrt2\,\sigma_a)$, and the density of the flip time is

$$p(\tau) = \frac{2\lambda}{\sqrt\pi}\,u\,e^{-u^2},$$

a Gumbel-like law with a sharp early edge and an exponential tail of late flips. Below, the
histograms and that density (left), and the flip time against $|a|$ on a logarithmic axis
(right), where every run lies on the straight line $t_f = \lambda^{-1}\ln(2A/|a|)$. The colours
mark which side of the separatrix a draw fell on ($H^2 > 2TI_2$: the polhode circles the major
axis, and $\omega_3$ keeps its sign; $H^2 < 2TI_2$: it circles the minor axis, and $\omega_1$
keeps its sign). Either way $\omega_2$ flips, at the same time: near the separatrix the side
decides only which transverse rate reverses with it."""),
    ("code", r"""
i1, i2, i3 = inertia  # nominal
lam0 = w * np.sqrt((i2 - i1) * (i3 - i2) / (i1 * i3))
kappa0 = np.sqrt((i2 - i1) * i1 / ((i3 - i2) * i3))
amp0 = w * np.sqrt(i2 * (i3 - i2) / (i1 * (i3 - i1)))
sigma_a = 0.5 * 1e-3 * np.sqrt(1 + kappa0**-2)
tau = np.linspace(10.0, 30.0, 400)
u = 2 * amp0 * np.exp(-lam0 * tau) / (np.sqrt(2) * sigma_a)
density = 2 * lam0 / np.sqrt(np.pi) * u * np.exp(-u**2)

# The same law as a distribution function, against the rates-only ensemble.
t_rates = np.sort(runs["rates only"].values["flip_1"])
u_runs = 2 * amp0 * np.exp(-lam0 * t_rates) / (np.sqrt(2) * sigma_a)
cdf = np.asarray(jax.scipy.special.erfc(u_runs))
ks = np.max(np.abs(cdf - np.arange(1, t_rates.size + 1) / t_rates.size))
print(f"Kolmogorov-Smirnov distance, rates only against the law: {ks:.3f} "
      f"(95% critical value {1.36 / np.sqrt(t_rates.size):.3f})")
assert ks < 1.36 / np.sqrt(t_rates.size)

fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5), layout="constrained")
bins = np.linspace(10.0, 30.0, 81)
for (name, res), colour in zip(runs.items(), ("tab:blue", "tab:orange", "k")):
    ax1.hist(res.values["flip_1"], bins=bins, density=True, histtype="step", lw=1.6,
             color=colour, label=name)
ax1.plot(tau, density, color="tab:red", ls="--", lw=1.5,
         label=r"law for $\varepsilon_{1,3} \sim \mathcal{N}(0, \sigma^2)$, nominal $I$")
ax1.set(xlabel="time of the first flip $t_f$ (s)", ylabel="probability density (1/s)",
        title=r"First flip of a spin about the intermediate axis ($\sigma = 10^{-3}$ rad/s)")
ax1.legend(loc="upper right", fontsize=9)

v = runs["both"].values
t_pred, a_abs, _, _ = linear_prediction(v["inertia"], v["omega0"])
major = np.asarray(jax.vmap(jd.separatrix_condition)(v["inertia"], v["omega0"])) > 0
ax2.semilogx(a_abs[major], v["flip_1"][major], ".", ms=3, color="tab:purple", alpha=0.6,
             label=rf"circles the major axis ({major.mean():.0%})")
ax2.semilogx(a_abs[~major], v["flip_1"][~major], ".", ms=3, color="tab:green", alpha=0.6,
             label=rf"circles the minor axis ({(~major).mean():.0%})")
a_line = np.logspace(np.log10(a_abs.min()), np.log10(a_abs.max()), 50)
ax2.semilogx(a_line, np.log(2 * amp0 / a_line) / lam0, color="k", lw=1.2,
             label=r"$t_f = \lambda^{-1}\ln(2A/|a|)$, nominal $I$")
ax2.set(xlabel=r"growing-mode amplitude $|a| = |\varepsilon_1 - \varepsilon_3/\kappa|/2$ (rad/s)",
        ylabel="time of the first flip $t_f$ (s)",
        title="Rates and 1% inertia spread: a logarithmic law")
ax2.legend(loc="upper right", fontsize=9)
for ax in (ax1, ax2):
    ax.grid(alpha=0.3, which="both")
plt.show()"""),
    ("md", r"""
The rate uncertainty dominates: the inertia spread alone moves the flip by a few tenths of a
second (through $\lambda$), while a Gaussian rate error spreads it over several seconds with a
long tail. Both kinds of draw, above and below the separatrix, lie on the same line."""),
    ("md", r"""
## 2. Staying within a cone: the major and minor axes

A spin about the major or the minor axis is stable: a small error in the rates makes the body's
axis *nutate*, wobbling around the fixed angular momentum $\mathbf{H}$ at a bounded angle. How
large a cone does it sweep? The observation below records, for each body axis $k$, the largest
angle over the run between the axis and $\mathbf{H}$, from the body-frame momentum
$\mathbf{h} = I\boldsymbol\omega$: $\theta_k = \mathrm{atan2}\big(\sqrt{|\mathbf{h}|^2 - h_k^2},
|h_k|\big)$.

The closed form comes from the polhode. About the major axis the energy and momentum integrals
give $h_1^2(1/I_1 - 1/I_3) + h_2^2(1/I_2 - 1/I_3) = 2T - H^2/I_3$; the polhode strays furthest
from axis 3 where $h_1 = 0$, so

$$\sin^2\theta_3^{\max} = \frac{2T - H^2/I_3}{H^2\,(1/I_2 - 1/I_3)}, \qquad
\sin^2\theta_1^{\max} = \frac{H^2/I_1 - 2T}{H^2\,(1/I_1 - 1/I_2)}$$

and likewise about the minor axis (furthest where $h_3 = 0$). In both cases the widest excursion
points towards the intermediate axis. About the intermediate axis there is no cone: the motion
follows the separatrix out to $\theta_2 = 90°$.

The same body $I = (1, 2, 2.7)$ kg m² (1% spread per moment), spinning at $w = 1$ rad/s about
each axis in turn, with transverse rate errors $\mathcal{N}(0, (0.02\,w)^2)$; 40 s covers 3 to 5
nutation periods."""),
    ("code", r"""
t_cone_end = 40.0
ts_cone = jnp.linspace(0.0, t_cone_end, 801)
sigma = 0.02  # transverse rate error (rad/s)


def cone_angles(traj):
    h = traj.angular_momentum  # body frame, (times, 3)
    h2 = jnp.sum(h**2, axis=-1, keepdims=True)
    angle = jnp.arctan2(jnp.sqrt(jnp.maximum(h2 - h**2, 0.0)), jnp.abs(h))
    return {"max_angle": jnp.max(jnp.where(traj.valid[:, None], angle, 0.0), axis=0),
            "omega0": traj.ys["omega"][0], "inertia": traj.scene.parameters()["inertia"]}


axes = {0: "minor", 1: "intermediate", 2: "major"}
cones = {}
for k, name in axes.items():
    unit = np.eye(3)[k]
    cones[name] = jd.ensemble(
        body, body.state(omega=w * unit), t_cone_end, n=2000, key=10 + k, ts=ts_cone,
        vary={"inertia": jd.LogNormal(inertia, 0.01),
              "omega": jd.Normal(w * unit, sigma * (1 - unit))},
        observe=cone_angles)
    assert cones[name].failed == 0
print(f"{3 * 2000} runs, compiled once in {cones['minor'].timing['compile_s']:.1f} s")"""),
    ("md", r"""
The check: each run's largest sampled angle against the closed form for its own inertia and
initial rates. The saved samples can only miss the peak by a little (0.05 s apart against
nutation periods of 8 to 11 s), so the sampled maximum lies just below the exact one."""),
    ("code", r"""
def cone_closed_form(inertia, omega0, k):
    i1, i2, i3 = inertia.T
    h = inertia * omega0
    hh = np.sum(h**2, axis=-1)
    two_t = np.sum(inertia * omega0**2, axis=-1)
    if k == 2:
        s2 = (two_t - hh / i3) / (hh * (1 / i2 - 1 / i3))
    elif k == 0:
        s2 = (hh / i1 - two_t) / (hh * (1 / i1 - 1 / i2))
    else:
        s2 = np.ones_like(hh)  # through the separatrix: the axis reaches 90 degrees from H
    return np.arcsin(np.sqrt(np.clip(s2, 0.0, 1.0)))


closed = {}
for k, name in axes.items():
    v = cones[name].values
    sim = v["max_angle"][:, k]
    closed[name] = cone_closed_form(v["inertia"], v["omega0"], k)
    rel = (closed[name] - sim) / closed[name]
    print(f"{name:>12} axis: median cone {np.degrees(np.median(sim)):6.3f} deg, sampled maximum "
          f"below the closed form by {rel.min():.1e} to {rel.max():.1e} (relative)")
    # About the intermediate axis the angle peaks in a cusp (h_2 passes through zero), which
    # samples 0.05 s apart can miss by about a degree.
    tol = 2e-2 if name == "intermediate" else 2e-3
    assert np.all(rel > -1e-9) and np.all(rel < tol), (name, rel.min(), rel.max())"""),
    ("code", r"""
fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5), layout="constrained")
colours = {"minor": "tab:blue", "intermediate": "tab:red", "major": "tab:green"}
bins = np.logspace(-2, np.log10(95), 80)
cone_deg = np.logspace(-2, np.log10(95), 400)
for k, name in axes.items():
    deg = np.degrees(cones[name].values["max_angle"][:, k])
    ax1.hist(deg, bins=bins, color=colours[name], alpha=0.6, label=f"spin about the {name} axis")
    if name == "intermediate":
        ax1.annotate(f"all {deg.size} runs flip:\n{deg.min():.1f} to {deg.max():.1f} deg",
                     xy=(85, 100), xytext=(55, 100), ha="right", va="center", fontsize=9,
                     color=colours[name],
                     arrowprops=dict(arrowstyle="->", color=colours[name]))
    p_sim = np.mean(deg[:, None] < cone_deg, axis=0)
    p_closed = np.mean(np.degrees(closed[name])[:, None] < cone_deg, axis=0)
    ax2.semilogx(cone_deg, p_sim, color=colours[name], lw=2, label=f"{name} axis, simulated")
    ax2.semilogx(cone_deg, p_closed, color="k", ls=":", lw=1.2,
                 label="closed form (polhode)" if k == 2 else None)
ax1.set_xscale("log")
ax1.set(xlabel=r"largest angle between the spin axis and $\mathbf{H}$ over 40 s (deg)",
        ylabel="runs per bin (of 2000)",
        title=rf"Nutation cones, transverse rate error $\sigma$ = {sigma} rad/s", ylim=(0, 200))
ax1.legend(loc="upper left", fontsize=9)
ax2.set(xlabel="cone half-angle (deg)", ylabel="P(the axis stays inside the cone)",
        title="Probability of staying within a cone", ylim=(-0.02, 1.02))
ax2.legend(loc="upper left", fontsize=9)
for ax in (ax1, ax2):
    ax.grid(alpha=0.3, which="both")
plt.show()

for c in (1.0, 2.0, 5.0):
    row = ", ".join(f"{name} {np.mean(np.degrees(cones[name].values['max_angle'][:, k]) < c):.3f}"
                    for k, name in axes.items())
    print(f"P(inside {c:.0f} deg): {row}")"""),
    ("md", r"""
For the same rate error, the major axis holds the tightest cone. The cone is roughly the
transverse share of the angular momentum, $I_\perp\sigma/(I_k w)$: about the major axis
$I_\perp/I_3 < 1$, about the minor axis $I_\perp/I_1 > 1$. Both
cone sizes scale linearly with $\sigma$, so the probability curves only shift along the log axis
with the rate error. About the intermediate axis the probability of staying in any cone short of
90° is zero within the 40 s: every run flips (section 1).

(Rigid and torque-free, the minor axis is stable. With any energy dissipation it is not: see the
major-axis rule in notebook 07.)"""),
    ("md", r"""
## 3. Rod fall times under random perturbations

The rod on frictionless ice of notebook 01 ($L = 1$ m), nearly upright: the initial angle is
log-normal, $\theta_0 \sim 10^{-3}\,e^{Z}$ rad (most draws between $10^{-4}$ and $10^{-2}$), with
a small random initial rate $\dot\theta_0 \sim \mathcal{N}(0, (10^{-3})^2)$ rad/s. The run ends at
the event `"flat"`, so the default observation `jd.final_state` already holds the fall time
`t_final`. Near upright $\ddot\theta \approx \lambda^2\theta$ with $\lambda = \sqrt{6g/L}$, and
the growing mode has amplitude $(\theta_0 + \dot\theta_0/\lambda)/2$: the fall time depends on
$\theta_0 + \dot\theta_0/\lambda$, logarithmically, and a negative sum makes the rod fall the other
way."""),
    ("code", r"""
rod = jd.FallingRod(length=1.0, mass=1.0, g=9.81)
ice = jd.Scene(rod)


def fall(traj):
    # Without save times a run keeps its start and its end: ys[...][0] is the drawn initial state.
    return {**jd.final_state(traj), "theta0": traj.ys["theta"][0],
            "theta_dot0": traj.ys["theta_dot"][0]}


falls = jd.ensemble(ice, ice.state(theta=1e-3), 5.0, n=3000, key=20,
                    vary={"theta": jd.LogNormal(1e-3, 1.0), "theta_dot": jd.Normal(0.0, 1e-3)},
                    observe=fall)
print(f"{falls.n} falls: {falls.status_counts()}; compile {falls.timing['compile_s']:.1f} s, "
      f"run {falls.timing['run_s']:.2f} s, {falls.timing['trajectories_per_s']:.0f} runs/s")
print("report keys:", sorted(falls.report()))
stats = falls.statistics["t_final"]
print("t_final (s): mean {mean:.4f}, std {std:.4f}, min {min:.4f}, max {max:.4f}".format(**stats),
      "| quantiles", {q: round(float(x), 4) for q, x in stats["quantiles"].items()})
assert np.all(falls.values["event.flat"])

# The fall time decreases monotonically with the angle, and the initial rate hardly matters at
# the median: the median fall time is the fall time of the median angle, 1e-3 rad.
t_median = float(rod.fall_time(1e-3))
print(f"median fall time {stats['quantiles']['50%']:.4f} s; from rest at 1e-3 rad {t_median:.4f} s")
assert abs(stats["quantiles"]["50%"] / t_median - 1) < 0.01"""),
    ("md", r"""
The check: `rod.fall_time(theta0, theta_dot0)` integrates the energy integral by quadrature (it
handles a negative initial rate, including the rod that rises, turns back and falls on the other
side), vectorised over all 3000 draws with `jax.vmap`."""),
    ("code", r"""
v = falls.values
t_quad = np.asarray(jax.jit(jax.vmap(rod.fall_time))(v["theta0"], v["theta_dot0"]))
rel = np.max(np.abs(v["t_final"] / t_quad - 1))
print(f"largest relative difference from the quadrature: {rel:.1e}")
assert rel < 1e-6, rel"""),
    ("code", r"""
lam = np.sqrt(6 * rod.g / rod.length)
side = np.sign(v["theta"])  # the flat angle: +pi/2 or -pi/2
amp = np.abs(v["theta0"] + v["theta_dot0"] / lam)
back = side < 0

fig, (ax1, ax2, ax3) = plt.subplots(1, 3, figsize=(15, 4.3), layout="constrained")
bins = np.linspace(0.7, np.percentile(v["t_final"], 99.8), 60)
ax1.hist(v["t_final"], bins=bins, color="tab:blue", alpha=0.7, label="simulated (events)")
ax1.hist(t_quad, bins=bins, histtype="step", color="k", lw=1.2, label="quadrature, same draws")
ax1.set(xlabel="fall time $T$ (s)", ylabel="runs per bin (of 3000)",
        title="Fall times of a 1 m rod")
ax1.legend(loc="upper right", fontsize=9)

ax2.semilogx(v["theta0"][~back], v["t_final"][~back], ".", ms=3, color="tab:blue", alpha=0.5,
             label="falls forward")
ax2.semilogx(v["theta0"][back], v["t_final"][back], ".", ms=5, color="tab:red",
             label=f"falls backward ({back.sum()} runs)")
ax2.set(xlabel=r"initial angle $\theta_0$ (rad)", ylabel="fall time $T$ (s)",
        title=r"Against $\theta_0$: the initial rate scatters the small angles")

grid = np.logspace(np.log10(amp.min()), np.log10(amp.max()), 200)
ax3.semilogx(amp[~back], v["t_final"][~back], ".", ms=3, color="tab:blue", alpha=0.5,
             label="falls forward")
ax3.semilogx(amp[back], v["t_final"][back], ".", ms=5, color="tab:red", label="falls backward")
ax3.semilogx(grid, np.asarray(jax.vmap(rod.fall_time)(jnp.asarray(grid))), color="k", lw=1.2,
             label=r"from rest at $\theta_0 = |\theta_0 + \dot\theta_0/\lambda|$")
ax3.set(xlabel=r"growing-mode amplitude $|\theta_0 + \dot\theta_0/\lambda|$ (rad)",
        ylabel="fall time $T$ (s)", title=r"Against the growing mode: one logarithmic law")
for ax in (ax2, ax3):
    ax.legend(loc="upper right", fontsize=9)
for ax in (ax1, ax2, ax3):
    ax.grid(alpha=0.3, which="both")
plt.show()"""),
    ("md", r"""
The histogram is skewed the same way as the flip times: the log-normal angle makes $\ln\theta_0$
Gaussian, so the bulk of the fall times is nearly Gaussian, and the draws where the initial rate
nearly cancels the angle ($\theta_0 + \dot\theta_0/\lambda \approx 0$) make a tail of late falls,
and some of them fall backward. Plotted against the growing-mode amplitude the scatter collapses
onto the fall time of a rod released from rest at that angle, to within the small decaying mode
that the released-from-rest curve ignores. The spread of the bulk is set by $\lambda$: with
$\ln\theta_0$ of standard deviation 1, the fall times have a standard deviation close to
$1/\lambda = \sqrt{L/6g} = 0.13$ s."""),
]


if __name__ == "__main__":
    build(MONTE_CARLO, HERE / "06_monte_carlo.ipynb")
