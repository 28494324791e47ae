"""Build `04_separatrix.ipynb` from the cell sources below (run: `python notebooks/_build_04.py`).

Written without outputs, with fixed cell ids, the same way `_build.py` builds 01 and 02;
`tests/test_notebooks.py` executes it.
"""

from pathlib import Path

from _build import build

HERE = Path(__file__).resolve().parent

SEPARATRIX = [
    ("md", r"""
# Separatrices on the momentum sphere: the free body and the gyrostat"""),
    ("md", r"""
A spinning body's angular momentum, seen from the body, wanders over a sphere of fixed radius
along the polhodes. A few special spins stay put: the relative equilibria. The stable ones are
centres that the polhodes circle; the unstable ones are saddles, and the curves through them, the
separatrices, divide the sphere into regions of qualitatively different motion. This notebook
finds the equilibria of any conservative rotational scene with `jd.find_equilibria` (Newton
iteration with automatic Jacobians), traces the separatrices with `jd.trace_separatrices`, and
follows them from the torque-free body to a gyrostat, a body carrying a spinning rotor, as the
rotor's momentum grows: the saddles move and then vanish. It finds the rotor momenta that
stabilise a spin about the intermediate axis with `jd.critical_rotor_momenta`, and shows the
period of the motion diverging as the initial condition approaches a separatrix. Closed forms,
the analytic stability condition and simulations check each result."""),
    ("code", r"""
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import jaxdyn as jd"""),
    ("code", r"""
# float64: the checks below compare against closed forms to ~1e-10, and the periods near the
# separatrix depend on energy differences of 1e-7 relative.
jd.enable_compilation_cache()  # compiled programs are reused by the next kernel
jax.config.update("jax_enable_x64", True)"""),
    ("md", r"""
## Relative equilibria and their stability

A gyrostat with principal moments $I$ and a rotor of constant momentum $\mathbf{h}_r$ (relative
to the body) obeys $I\dot{\boldsymbol\omega} = (I\boldsymbol\omega + \mathbf{h}_r)\times
\boldsymbol\omega$; with $\mathbf{h}_r = 0$ this is the torque-free body. Both the length of the
total momentum $\mathbf{h} = I\boldsymbol\omega + \mathbf{h}_r$ and the kinetic energy
$T = \tfrac12\boldsymbol\omega\cdot I\boldsymbol\omega$ are conserved, so $\mathbf{h}$ moves on
the sphere $|\mathbf{h}| = H$ along the level curves of $T$.

A relative equilibrium is a fixed point $\dot{\boldsymbol\omega} = f(\boldsymbol\omega) = 0$,
here $\mathbf{h} \parallel \boldsymbol\omega$. Fixed points come in one-parameter families (a spin
about a principal axis at any rate), which cross the sphere at isolated points, so
`jd.find_equilibria` solves the square system $f(\boldsymbol\omega) + (|\mathbf{h}| - H)\,\hat n =
0$, with $\hat n$ the sphere's normal, by Newton iteration from 64 points spread over the sphere.
It uses only the scene's vector field and invariants: nothing in it knows about rotors or
principal axes. The linearisation $J = \partial f/\partial\boldsymbol\omega$, restricted to the
sphere's tangent plane, has eigenvalues $\pm\lambda$: a real pair for a saddle, an imaginary pair
for a centre.

For the torque-free body with $I_1 < I_2 < I_3$ the answer is classical: centres
$\boldsymbol\omega = \pm (H/I_k)\,\hat e_k$ on the minor and major axes, saddles on the
intermediate axis with

$$\lambda^2 = \Omega^2\,\frac{(I_2 - I_1)(I_3 - I_2)}{I_1 I_3},\qquad \Omega = H/I_2,$$

and the separatrix energy $T_s = H^2/(2I_2)$."""),
    ("code", r"""
inertia = jnp.array([1.0, 2.0, 3.0])
moments = np.asarray(inertia)
i1, i2, i3 = moments
H = 1.0
body = jd.RigidBody(inertia)
plain = jd.Scene(body)
eq = jd.find_equilibria(plain, H)

for w, energy, kind, ev in zip(np.asarray(eq.omega), np.asarray(eq.energy), eq.kind,
                               np.asarray(eq.eigenvalues)):
    w = np.where(np.abs(w) < 1e-12, 0.0, w)  # round-off about exact zeros
    print(f"{kind:6s}  omega = {np.array2string(w, precision=4):24s}  T = {energy:.6f}  "
          f"eigenvalues = +-{abs(ev[0]):.6f}{'' if kind == 'saddle' else ' i'}")

# Against the closed form.
saddles = np.asarray(eq.omega)[eq.is_saddle]
assert np.allclose(np.sort(saddles[:, 1]), [-H / i2, H / i2], rtol=1e-12)
assert np.allclose(saddles[:, [0, 2]], 0.0, atol=1e-12)
assert np.allclose(eq.separatrix_energies, [H**2 / (2 * i2)], rtol=1e-12)
sigma = (H / i2) * np.sqrt((i2 - i1) * (i3 - i2) / (i1 * i3))
assert np.allclose(np.asarray(eq.growth_rate)[eq.is_saddle], sigma, rtol=1e-12)
print(f"separatrix energy {float(eq.separatrix_energies[0]):.12f} "
      f"(closed form H^2/(2 I_2) = {H**2 / (2 * i2):.12f})")"""),
    ("md", r"""
## Tracing the separatrices

The separatrices are the saddles' unstable manifolds. `jd.trace_separatrices` starts a
simulation a tiny step ($10^{-7}$ of the rates) from each saddle along $\pm$ its unstable
eigenvector and follows it until it comes back to a saddle; each branch is resampled evenly in
arc length. For the torque-free body the branches are heteroclinic, from one saddle to the other,
and the separatrix is known in closed form: $H^2 = 2TI_2$, which `jd.separatrix_condition`
evaluates without cancellation."""),
    ("code", r"""
sep = jd.trace_separatrices(plain, eq)
cond = np.asarray(jd.separatrix_condition(inertia, sep.omega))
on_sphere = np.abs(np.linalg.norm(np.asarray(sep.angular_momentum), axis=-1) - H)
assert bool(np.all(sep.returned)) and np.all(np.asarray(sep.end_saddle) != np.asarray(sep.saddle))
assert np.max(np.abs(cond)) < 1e-9 and np.max(on_sphere) < 1e-9
print(f"{len(sep)} branches, each {float(sep.duration[0]):.1f} s long; "
      f"max |H^2 - 2 T I_2| = {np.max(np.abs(cond)):.1e}, "
      f"max ||h| - H| = {np.max(on_sphere):.1e}")"""),
    ("md", r"""
## Polhode portraits

Polhodes are simulated from starting points on the $h_1h_3$ great circle, each drawn over one
period (up to its first return to the starting point, found on a Poincaré section). The same
helper measures periods later on. Every simulation keeps the same number of saved times, so one
compilation serves each scene structure."""),
    ("code", r"""
NUM = 4001  # saved times per run: one length for every run below, so no recompilation
tight = dict(rtol=1e-10, atol=1e-12)


def rotor_of(scene):
    # The rotor's momentum: the total momentum with the body at rest.
    return np.asarray(scene.outputs(0.0, scene.state(omega=jnp.zeros(3)))["angular_momentum"])


def run(scene, h0, t1):
    # Simulate from the total momentum h0 on the sphere; times and momenta along the way.
    w0 = (h0 - rotor_of(scene)) / moments
    traj = jd.simulate(scene, scene.state(omega=w0), t1, ts=jnp.linspace(0.0, t1, NUM),
                       dense=True, **tight)
    return np.asarray(traj.ts), np.asarray(traj.angular_momentum)


def first_return(t, h):
    # Index and time of the first return to h[0]: the first crossing, close to h[0], of the
    # plane through h[0] normal to the initial velocity, in the initial direction (the orbit
    # may cross that plane elsewhere too). The time by cubic inverse interpolation.
    normal = h[1] - h[0]
    s = (h - h[0]) @ normal / np.linalg.norm(normal)
    dist = np.linalg.norm(h - h[0], axis=1)
    far = dist > 0.05 * np.linalg.norm(h[0])
    left = np.argmax(far)
    close = dist[:-1] < 2 * np.max(np.linalg.norm(np.diff(h, axis=0), axis=1))
    back = np.flatnonzero((s[:-1] < 0) & (s[1:] >= 0) & close & (np.arange(len(s) - 1) > left))
    if not far.any() or back.size == 0:
        return len(t) - 1, np.inf
    i = back[0]
    k = slice(max(i - 1, 0), i + 3)
    return i + 1, float(np.polyval(np.polyfit(s[k], t[k], 3), 0.0))


def polhodes(scene, starts, t1=60.0):
    curves = []
    for h0 in starts:
        t, h = run(scene, h0, t1)
        end, period = first_return(t, h)
        # One period, closed; an orbit slower than t1 (close to a separatrix) as far as it got.
        curves.append(np.vstack([h[: end + 1], h[:1]]) if np.isfinite(period) else h)
    return curves


angles = np.radians(np.arange(0.0, 360.0, 12.0) + 4.0)
starts = H * np.stack([np.sin(angles), np.zeros_like(angles), np.cos(angles)], axis=1)
curves = polhodes(plain, starts)
# Every polhode lies on the sphere and on its own energy ellipsoid h.I^-1.h = 2T.
for c in curves:
    assert np.max(np.abs(np.linalg.norm(c, axis=1) - H)) < 1e-8
    two_t = np.sum(c**2 / moments, axis=1)
    assert np.max(np.abs(two_t - two_t[0])) < 1e-8"""),
    ("code", r"""
def view_vector(elev, azim):
    e, a = np.radians(elev), np.radians(azim)
    return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def draw(ax, curve, view, label=None, **style):
    # Solid on the near side of the sphere, faint on the far side.
    near = (curve @ view >= 0)[:, None]
    ax.plot(*np.where(near, curve, np.nan).T, label=label, **style)
    ax.plot(*np.where(near, np.nan, curve).T, alpha=0.15, **style)


def portrait(ax, scene, eq, sep, curves, elev=22, azim=-58, zoom=1.3):
    view = view_vector(elev, azim)
    r = float(eq.momentum)
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 60), np.linspace(0, np.pi, 30))
    ax.plot_surface(r * np.cos(u) * np.sin(v), r * np.sin(u) * np.sin(v), r * np.cos(v),
                    color="lightsteelblue", alpha=0.12, linewidth=0, shade=False)
    e_a = np.cross(view, [0.0, 0.0, 1.0])
    e_a /= np.linalg.norm(e_a)
    psi = np.linspace(0, 2 * np.pi, 200)[:, None]
    ax.plot(*(r * (np.cos(psi) * e_a + np.sin(psi) * np.cross(view, e_a))).T, color="gray",
            lw=0.8)
    for k, name in enumerate(["$h_1$", "$h_2$", "$h_3$"]):  # body axes, through the sphere
        tip = np.zeros(3)
        tip[k] = 1.3 * r
        ax.plot(*np.stack([-tip, tip]).T, color="gray", lw=0.6, ls=":")
        ax.text(*(1.08 * tip), name, color="dimgray", ha="center", va="center")
    for k, c in enumerate(curves):
        draw(ax, c, view, label="polhodes (simulated)" if k == 0 else None, color="tab:blue",
             lw=1.0)
    for k, c in enumerate(np.asarray(sep.angular_momentum)):
        draw(ax, c, view, label="separatrices (traced)" if k == 0 else None, color="crimson",
             lw=2.5)
    h_eq = moments * np.asarray(eq.omega) + rotor_of(scene)
    for kind, marker, color in (("center", "o", "tab:green"), ("saddle", "X", "k")):
        pts = h_eq[np.array([k == kind for k in eq.kind], dtype=bool)]
        near = pts @ view >= 0
        ax.scatter(*pts[near].T, marker=marker, s=70, color=color, depthshade=False, zorder=5,
                   label=f"{kind}s" if len(pts) else None)
        ax.scatter(*pts[~near].T, marker=marker, s=70, color=color, alpha=0.25,
                   depthshade=False, zorder=5)
    ax.set(xlim=(-r, r), ylim=(-r, r), zlim=(-r, r))
    ax.set_box_aspect((1, 1, 1), zoom=zoom)
    ax.set_axis_off()
    ax.view_init(elev=elev, azim=azim)


fig = plt.figure(figsize=(7.5, 7.5), layout="constrained")
ax = fig.add_subplot(projection="3d", proj_type="ortho")
portrait(ax, plain, eq, sep, curves, zoom=1.15)
ax.set_title("Torque-free body, $I = (1, 2, 3)$ kg m², on $|\\mathbf{h}| = 1$ N m s\n"
             "(far side of the sphere drawn faint)")
ax.legend(loc="upper left")
plt.show()"""),
    ("md", r"""
## The gyrostat: saddles move and vanish

Put a rotor along the major axis, $\mathbf{h}_r = h\,\hat e_3$. The equilibria satisfy
$\mathbf{h} = \mu\boldsymbol\omega$ for some $\mu$, so $h_i(\mu - I_i) = \mu h_{r,i}$. Besides
the two spins about axis 3 ($h_3 = \pm H$), for each $i = 1, 2$ the choice $\mu = I_i$ gives a
pair with

$$h_3 = \frac{I_i h}{I_i - I_3},\qquad h_i = \pm\sqrt{H^2 - h_3^2},$$

which exists only while $|I_i h| < |I_i - I_3|\,H$. As $h$ grows the intermediate-axis saddles
($i = 2$) slide towards $-\hat e_3$, merge with the spin there at $h = H/2$ and leave it a
saddle; the minor-axis centres ($i = 1$) follow and merge at $h = 2H$, after which only the two
spins about axis 3 remain, both stable. The portraits below are drawn from below the sphere's
equator, where this happens; the count of equilibria is checked against the formula, and the
spins about axis 3 against their analytic stability condition (next section)."""),
    ("code", r"""
def expected_count(h):
    return 2 + sum(2 for i in (0, 1) if abs(moments[i] * h) < abs(moments[i] - i3) * H)


gyro = jd.Scene(body, (jd.Rotor(jnp.zeros(3)),))
rotor_values = [0.2, 0.45, 0.7, 2.5]
panels = []
for h in rotor_values:
    scene = gyro.replace({"rotor.momentum": jnp.array([0.0, 0.0, h])})
    eq_h = jd.find_equilibria(scene, H)
    sep_h = jd.trace_separatrices(scene, eq_h)
    assert len(eq_h) == expected_count(h), (h, len(eq_h))
    # Independently: h = I w + h_r is parallel to w and on the sphere.
    h_eq = moments * np.asarray(eq_h.omega) + rotor_of(scene)
    assert np.allclose(np.cross(h_eq, np.asarray(eq_h.omega)), 0.0, atol=1e-12)
    assert np.allclose(np.linalg.norm(h_eq, axis=1), H, rtol=1e-12)
    # Each traced branch stays on the sphere at its saddle's energy.
    w = np.asarray(sep_h.omega)
    if len(sep_h):
        energy = 0.5 * np.sum(moments * w**2, axis=-1)
        assert np.allclose(energy, np.asarray(sep_h.energy)[:, None], rtol=1e-9)
    panels.append((h, scene, eq_h, sep_h, polhodes(scene, starts)))
    print(f"h = {h:4}: {eq_h.kind.count('saddle')} saddle(s), {eq_h.kind.count('center')} centers, "
          f"separatrix energies {np.round(np.asarray(eq_h.separatrix_energies), 6)}, "
          f"{len(sep_h)} traced branches")

fig = plt.figure(figsize=(10, 10.5), layout="constrained")
for k, (h, scene, eq_h, sep_h, curves_h) in enumerate(panels):
    ax = fig.add_subplot(2, 2, k + 1, projection="3d", proj_type="ortho")
    portrait(ax, scene, eq_h, sep_h, curves_h, elev=-30, azim=-58)
    n = eq_h.kind.count("saddle")
    ax.set_title(f"rotor $h$ = {h} N m s along $\\hat e_3$: {n} saddle{'' if n == 1 else 's'}, "
                 f"{eq_h.kind.count('center')} centers")
fig.legend(*fig.axes[0].get_legend_handles_labels(), loc="outside lower center", ncols=4)
fig.suptitle("Gyrostat $I = (1, 2, 3)$ kg m² on $|\\mathbf{h}| = 1$ N m s, seen from below "
             "(far side faint)")
plt.show()"""),
    ("md", r"""
## Critical rotor momenta: stabilising the intermediate axis

Spin the body at rate $W$ about axis $K$ with the rotor along the same axis. Linearising about
$\boldsymbol\omega = W\hat e_K$, with $i, j$ the two other axes,

$$\lambda^2 = -\frac{(I_K W + h - I_i W)(I_K W + h - I_j W)}{I_i I_j},$$

so the spin is stable where $(I_K W + h - I_i W)(I_K W + h - I_j W) > 0$ and stability changes at
$h = (I_i - I_K)W$ and $h = (I_j - I_K)W$. `jd.critical_rotor_momenta` does not use this formula:
it differentiates the scene's vector field for $\lambda^2(h)$ and finds its roots by Newton
iteration. Below, its answers against the formula for a few bodies, then a check by simulation:
a spin about the intermediate axis of $I = (1, 2, 3)$ at $W = 1$ rad/s, nudged by
$\delta\omega_1 = 10^{-6}$ rad/s,
for a range of rotor momenta."""),
    ("code", r"""
def analytic_roots(m, axis, rate):
    others = [k for k in range(3) if k != axis]
    return np.sort([(m[k] - m[axis]) * rate for k in others])


for m, axis, rate in [([1.0, 2.0, 3.0], 1, 1.0), ([1.4, 2.2, 1.1], 0, -0.8),
                            ([2.7, 1.9, 1.6], 2, 3.1)]:
    found = np.asarray(jd.critical_rotor_momenta(jnp.asarray(m), axis, rate))
    assert np.allclose(found, analytic_roots(np.asarray(m), axis, rate), rtol=1e-10)
    print(f"I = {m}, axis {axis + 1}, W = {rate:5}: critical h = {np.round(found, 10)}")

rate = 1.0
critical = np.asarray(jd.critical_rotor_momenta(inertia, 1, rate))
h_scan = np.linspace(-2.5, 2.5, 41)
e2 = jnp.array([0.0, 1.0, 0.0])
eps, t_scan = 1e-6, 60.0
growth = []
for h in h_scan:
    scene = gyro.replace({"rotor.momentum": h * e2})
    w0 = jnp.array([eps, rate, 0.0])  # excites both transverse eigenvectors
    traj = jd.simulate(scene, scene.state(omega=w0), t_scan,
                       ts=jnp.linspace(0.0, t_scan, NUM), dense=True, **tight)
    growth.append(np.max(np.abs(np.asarray(traj.omega)[:, [0, 2]])) / eps)
growth = np.array(growth)
unstable = (h_scan > critical[0]) & (h_scan < critical[1])
margin = np.minimum(np.abs(h_scan - critical[0]), np.abs(h_scan - critical[1])) > 0.1
assert np.all(growth[unstable & margin] > 1e3) and np.all(growth[~unstable & margin] < 10)

fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5), layout="constrained")
h_fine = np.linspace(-2.5, 2.5, 400)
lam2 = -((i2 * rate + h_fine - i1 * rate) * (i2 * rate + h_fine - i3 * rate)) / (i1 * i3)
ax1.plot(h_fine, lam2, color="k", lw=1.5, label=r"analytic $\lambda^2(h)$")
ax1.axhline(0, color="gray", lw=0.8)
for k, hc in enumerate(critical):
    ax1.plot(hc, 0.0, "o", color="crimson", ms=9, mfc="none", mew=2,
             label="jd.critical_rotor_momenta" if k == 0 else None)
ax1.set(xlabel="rotor momentum $h$ (N m s)", ylabel=r"$\lambda^2$ (s$^{-2}$)",
        title="Spin about the intermediate axis: unstable where $\\lambda^2 > 0$")
ax1.legend(loc="lower center")
ax2.semilogy(h_scan, growth, "o-", color="tab:blue", ms=4, lw=1)
for ax in (ax1, ax2):
    ax.axvspan(*critical, color="crimson", alpha=0.08)
    ax.grid(alpha=0.3)
ax2.set(xlabel="rotor momentum $h$ (N m s)", ylabel=r"max $|\delta\omega_{1,3}|\,/\,10^{-6}$",
        title=f"Simulated: largest transverse rate over {t_scan:.0f} s")
plt.show()
print(f"critical rotor momenta {critical} N m s; the spin is unstable between them (shaded)")"""),
    ("md", r"""
## The period diverges at the separatrix

Near a saddle the motion is hyperbolic: in coordinates $x, y$ along the unstable and stable
directions the energy is $T - T_s \propto xy$, so an orbit with energy offset $\Delta T$ takes
$\lambda^{-1}\ln(1/\Delta T) + \text{const}$ to pass the saddle. An orbit close to the separatrix
passes $n$ saddles per period, and its period grows like

$$P \approx \frac{n}{\lambda}\ln\frac{1}{|\Delta T|} + \text{const}.$$

For the torque-free body every orbit near the separatrix passes both saddles ($n = 2$). For the
gyrostat with $h = 0.7$ N m s the separatrix is a figure of eight through one saddle at
$-\hat e_3$: an orbit inside one of its lobes passes the saddle once per period ($n = 1$), an orbit
outside both lobes twice ($n = 2$). Starting points on the $h_1h_3$ great circle at relative energy
offsets from $10^{-1}$ to $10^{-7}$; the torque-free periods are checked against the closed form
`jd.torque_free_period`, the gyrostat's slopes against $n/\lambda$ with $\lambda$ from the
finder."""),
    ("code", r"""
def meridian(a):
    return H * np.array([np.sin(a), 0.0, np.cos(a)])


def energy_at(scene, a):
    # Kinetic energy at the points h = H (sin a, 0, cos a) of the h_1 h_3 great circle.
    a = np.asarray(a)[..., None]
    w = (H * np.concatenate([np.sin(a), 0 * a, np.cos(a)], axis=-1) - rotor_of(scene)) / moments
    return 0.5 * np.sum(moments * w**2, axis=-1)


def angle_at(scene, targets, lo, hi):
    # Angles in [lo, hi], where the energy is monotonic, at the target energies (bisection).
    targets = np.asarray(targets, dtype=float)
    lo, hi = np.full_like(targets, lo), np.full_like(targets, hi)
    rising = energy_at(scene, hi[:1])[0] > energy_at(scene, lo[:1])[0]
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        below = (energy_at(scene, mid) < targets) == rising
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return 0.5 * (lo + hi)


def free_period(a):
    # Closed-form period of the torque-free body started at angle a on the great circle.
    return float(jd.torque_free_period(inertia, jnp.asarray(meridian(a) / moments)))


def periods(scene, t_sep, lam, n, side, lo, hi, offsets):
    out = []
    for d, a in zip(offsets, angle_at(scene, t_sep * (1 + side * offsets), lo, hi)):
        t1 = n / lam * np.log(1 / d) + 40.0 / lam  # generous: the law plus a margin
        t, h = run(scene, meridian(a), t1)
        out.append(first_return(t, h)[1])
    return np.array(out)


offsets = np.logspace(-1, -7, 7)
cases = {}
# Torque-free body: the separatrix crosses the meridian at 30 degrees; two saddles per period.
t_sep, lam = float(eq.separatrix_energies[0]), float(np.max(eq.growth_rate))
for side, (lo, hi) in ((-1, (0.0, np.pi / 6)), (1, (np.pi / 6, np.pi / 2))):
    cases["free", side] = periods(plain, t_sep, lam, 2, side, lo, hi, offsets)
# Gyrostat, h = 0.7: outside the lobes below the separatrix energy, inside above it.
gyro7 = panels[2][1]
eq7 = panels[2][2]
t_sep7, lam7 = float(eq7.separatrix_energies[0]), float(np.max(eq7.growth_rate))
h_eq7 = moments * np.asarray(eq7.omega) + rotor_of(gyro7)
a_lobe = np.arctan2(*h_eq7[h_eq7[:, 0] > 0.5][0, ::2])  # the lobe's center with h_1 > 0
a_cross = float(angle_at(gyro7, [t_sep7], 0.0, a_lobe)[0])
n7 = {-1: 2, 1: 1}
for side, (lo, hi) in ((-1, (0.0, a_cross)), (1, (a_cross, a_lobe))):
    cases["gyro", side] = periods(gyro7, t_sep7, lam7, n7[side], side, lo, hi, offsets)

# Checks: the torque-free periods against the closed form, the gyrostat's slopes against n/lam.
closed = {}
for side, (lo, hi) in ((-1, (0.0, np.pi / 6)), (1, (np.pi / 6, np.pi / 2))):
    a = angle_at(plain, t_sep * (1 + side * offsets), lo, hi)
    closed[side] = np.array([free_period(x) for x in a])
    assert np.max(np.abs(cases["free", side] / closed[side] - 1)) < 1e-5
w3 = float(np.asarray(eq7.omega)[eq7.is_saddle][0, 2])  # the spin about -e_3: h_3 = -H
lam7_exact = np.sqrt(-(-H - i1 * w3) * (-H - i2 * w3) / (i1 * i2))
assert abs(lam7 / lam7_exact - 1) < 1e-10
for side in (-1, 1):
    p = cases["gyro", side]
    slope = (p[-1] - p[-2]) / np.log(offsets[-2] / offsets[-1])
    assert abs(slope * lam7 / n7[side] - 1) < 1e-2, (side, slope * lam7 / n7[side])
    print(f"gyrostat {'inside' if side > 0 else 'outside'} the lobes: slope {slope:.4f} s, "
          f"n/lambda = {n7[side] / lam7:.4f} s")"""),
    ("code", r"""
fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.8), layout="constrained")
fine = np.logspace(-1, -7, 60)
for side, color in ((-1, "tab:blue"), (1, "tab:orange")):
    where = "below" if side < 0 else "above"
    lo, hi = (0.0, np.pi / 6) if side < 0 else (np.pi / 6, np.pi / 2)
    a = angle_at(plain, t_sep * (1 + side * fine), lo, hi)
    p_closed = [free_period(x) for x in a]
    ax1.semilogx(fine, p_closed, color=color, lw=1.5, ls="-" if side < 0 else "--",
                 label=f"closed form, {where} $T_s$")
    ax1.semilogx(offsets, cases["free", side], "o", color=color, ms=8, mfc="none", mew=1.5,
                 label=f"simulated, {where} $T_s$")
    p = cases["gyro", side]
    label = "inside a lobe" if side > 0 else "outside the lobes"
    ax2.semilogx(offsets, p, "o", color=color, ms=8, mfc="none", mew=1.5,
                 label=f"simulated, {label} ($n$ = {n7[side]})")
    c = p[-1] - n7[side] / lam7 * np.log(1 / offsets[-1])
    ax2.semilogx(fine, n7[side] / lam7 * np.log(1 / fine) + c, color=color, ls="--", lw=1,
                 label=rf"$({n7[side]}/\lambda)\ln(1/|\Delta T|)$ + const")
ax1.set(title=f"Torque-free body: two saddles per period ($\\lambda$ = {lam:.4f} s$^{{-1}}$)")
ax2.set(title=f"Gyrostat, $h$ = 0.7 N m s: one saddle ($\\lambda$ = {lam7:.4f} s$^{{-1}}$)")
for ax in (ax1, ax2):
    ax.invert_xaxis()
    ax.set(xlabel=r"relative energy offset $|T - T_s|\,/\,T_s$", ylabel="period $P$ (s)")
    ax.grid(alpha=0.3, which="major")
    ax.legend(loc="upper left", fontsize=9)
plt.show()"""),
]


if __name__ == "__main__":
    build(SEPARATRIX, HERE / "04_separatrix.ipynb")
