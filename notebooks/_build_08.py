"""Build `08_rough_floor.ipynb` from the cell sources below (run: `python notebooks/_build_08.py`).

Written without outputs, with fixed cell ids, by `_build.build`; `tests/test_notebooks.py`
executes it.
"""

from pathlib import Path

from _build import build

HERE = Path(__file__).resolve().parent

ROUGH = [
    ("md", r"""
# The rod on a rough floor: stick, slip and lift-off"""),
    ("md", r"""
A rod standing almost upright on a rough floor first pivots about its tip, held by friction. As it
falls, the friction needed to hold the tip grows faster than the normal force, and at some angle
it exceeds what static friction can give: the tip slips, backward or forward depending on the
friction coefficient. This notebook simulates the whole story with `jd.RoughFloorRod`, a hybrid
body whose modes (stick, slip, flight) switch at events located by root finding, and checks the
slip onset against the contact forces of the pivoting rod in closed form, the energy balance
against the work of kinetic friction, and the frictionless limit against the falling rod on
ice."""),
    ("code", r"""
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import jaxdyn as jd"""),
    ("code", r"""
# float64: the slip angles are compared with closed forms to ~1e-9, and the energy balance to
# ~1e-8 of the rod's potential energy.
jd.enable_compilation_cache()  # compiled programs are reused by the next kernel
jax.config.update("jax_enable_x64", True)"""),
    ("md", r"""
## The pivoting rod and the friction it needs

While the tip sticks, the rod of length $L$ and mass $m$ pivots about it:
$I_\text{tip}\ddot\theta = mg\tfrac{L}{2}\sin\theta$ with $I_\text{tip} = mL^2/3$, so
$\ddot\theta = \tfrac{3g}{2L}\sin\theta$, and from rest at $\theta_0$ the energy gives
$\dot\theta^2 = \tfrac{3g}{L}(\cos\theta_0 - \cos\theta)$. The centre of mass (CM) moves on a
circle about the tip, and the floor supplies the force that the CM's acceleration needs
($\mathbf{F} = m\mathbf{a}_c$): a friction force $F$ along $x$ and a normal force $N$,

$$F = \tfrac34 mg\sin\theta\,(3\cos\theta - 2\cos\theta_0),\qquad
N = \tfrac14 mg\,(1 + 9\cos^2\theta - 6\cos\theta_0\cos\theta).$$

Early in the fall $F > 0$: the floor pushes the tip towards the side the rod falls to, so without
friction the tip would slide *backward*. Past $\cos\theta = \tfrac23\cos\theta_0$ (about 48°)
$F$ changes sign, and the tip would slide *forward*. From upright, $N = \tfrac14 mg(3\cos\theta -
1)^2$ vanishes at $\cos\theta = 1/3$ (70.5°), so $|F|/N$ grows without bound there: every rod
slips before that. The tip slips where $|F| = \mu_s N$ first. `rod.pivot_forces` evaluates these
forces from the energy integral; here they are checked against the formulas above."""),
    ("code", r"""
rod = jd.RoughFloorRod(length=1.0, mass=1.0, g=9.81, mu_s=0.5, mu_k=0.4)
m, L, g = 1.0, 1.0, 9.81
theta0 = 0.05
theta = np.linspace(theta0, np.arccos(1 / 3) - 0.02, 2000)
forces = rod.pivot_forces(theta, theta0)
f, n = np.asarray(forces["friction_force"]), np.asarray(forces["normal_force"])
c, c0 = np.cos(theta), np.cos(theta0)
assert np.allclose(f, 0.75 * m * g * np.sin(theta) * (3 * c - 2 * c0), atol=1e-12)
assert np.allclose(n, 0.25 * m * g * (1 + 9 * c**2 - 6 * c0 * c), atol=1e-12)

ratio = f / n
first = theta < np.arccos(2 * c0 / 3)
r_max = ratio[first].max()
print(f"|F|/N peaks at {r_max:.4f} (theta = {np.degrees(theta[first][ratio[first].argmax()]):.1f}"
      f" deg) while F > 0: below that mu_s the tip slips backward")

fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.3), layout="constrained")
deg = np.degrees(theta)
ax1.plot(deg, f / (m * g), color="tab:red", label="friction needed $F/mg$")
ax1.plot(deg, n / (m * g), color="tab:green", label="normal force $N/mg$")
for mu, ls in ((0.2, ":"), (0.5, "--")):
    ax1.plot(deg, mu * n / (m * g), color="0.35", ls=ls, lw=1, label=rf"$\mu_s N/mg$, $\mu_s$={mu}")
    ax1.plot(deg, -mu * n / (m * g), color="0.35", ls=ls, lw=1)
ax1.axhline(0, color="k", lw=0.5)
ax1.set(xlabel=r"$\theta$ (deg)", ylabel="force / weight",
        title="Contact forces of the pivoting rod (from rest at 0.05 rad)")
ax1.legend(loc="lower left", fontsize=9)
ax2.plot(deg, np.abs(ratio), color="tab:purple")
ax2.axhline(r_max, color="0.5", ls=":", lw=1)
ax2.annotate(f"peak {r_max:.3f}", (np.degrees(theta[first][ratio[first].argmax()]), r_max),
             textcoords="offset points", xytext=(-20, 8))
ax2.axvline(np.degrees(np.arccos(2 * c0 / 3)), color="0.5", ls="--", lw=1)
ax2.text(np.degrees(np.arccos(2 * c0 / 3)) + 1, 1.6, "F changes sign", fontsize=9)
ax2.set(xlabel=r"$\theta$ (deg)", ylabel=r"$|F|/N$", ylim=(0, 2),
        title=r"Friction ratio needed: the tip slips where it first reaches $\mu_s$")
for ax in (ax1, ax2):
    ax.grid(alpha=0.3)
plt.show()"""),
    ("md", r"""
## The hybrid simulation

`jd.simulate` runs a hybrid body as segments: each is integrated until one of the current mode's
events reaches zero (stick: $|F| = \mu_s N$; slip: the tip comes to rest, or $N = 0$; flight: the
rod touches the floor again; any contact mode: the rod lies flat), located by root finding, and
then the body maps the state into the next mode. While sliding, kinetic friction
$-\mu_k N\,\mathrm{sign}(v_\text{tip})$ acts, and the equations of motion follow from
$\dot H_c = L_c$, $\mathbf{F} = m\mathbf{a}_c$ and the tip staying on the floor. The whole run is
one traced computation, so `jax.vmap` sweeps the friction coefficient in one compiled call. Here
$\mu_k = 0.8\,\mu_s$, and three more runs ride along in the same batch: a rod flung towards
upright fast enough to leave the floor, and the frictionless floor."""),
    ("code", r"""
scene = jd.Scene(rod)
t1 = 1.2
ts = jnp.linspace(0.0, t1, 481)


@jax.jit
@jax.vmap
def run(mu_s, mu_k, theta0, theta_dot0):
    sc = scene.replace(mu_s=mu_s, mu_k=mu_k)
    traj = jd.simulate(sc, sc.state(theta=theta0, theta_dot=theta_dot0), t1, ts=ts,
                       rtol=1e-11, atol=1e-12)
    out = traj.outputs()
    keep = ("theta", "tip_x", "tip_height", "top_x", "top_height", "mode",
            "mechanical_energy", "friction_work", "energy")
    return {
        "y_final": traj.y_final,
        "t_final": traj.t_final,
        "flat": traj.event["flat"],
        "ts": traj.ts,
        **{k: out[k] for k in keep},
    }


mus = np.linspace(0.02, 1.2, 60)
extra = np.array([  # mu_s, mu_k, theta0, theta_dot0
    [0.5, 0.4, 0.8, -5.0],  # turning towards upright fast: slips, then lifts off
    [0.0, 0.0, 0.05, 0.0],  # frictionless
    [0.365, 0.3, 0.05, 0.0],  # slips backward, sticks again, slips forward
])
batch = np.concatenate([np.stack([mus, 0.8 * mus, 0 * mus + theta0, 0 * mus], 1), extra])
res = jax.tree.map(np.asarray, run(*(jnp.asarray(col) for col in batch.T)))
slip_theta, slip_dir = res["y_final"]["slip_theta"], res["y_final"]["slip_direction"]
n = len(mus)
print(f"{len(batch)} runs; all reached the floor: {bool(res['flat'][:n].all())}")"""),
    ("md", r"""
## Slip angle and direction against the friction coefficient

The closed-form prediction: the first angle where $|F|/N$ of the pivoting rod reaches $\mu_s$,
found by bisection on the formulas above (no simulation). The simulated slip angle is the
root of the stick mode's event $\mu_s N - |F| = 0$ located during the integration."""),
    ("code", r"""
def predicted(mu_s):
    # First crossing of |F| - mu_s N on a grid, then bisection, on the closed-form forces.
    def excess(th):
        c = np.cos(th)
        f = 0.75 * np.sin(th) * (3 * c - 2 * c0)
        n = 0.25 * (1 + 9 * c**2 - 6 * c0 * c)
        return np.abs(f) - mu_s * n

    grid = np.linspace(theta0, np.arccos(1 / 3), 40001)
    i = np.argmax(excess(grid) > 0)
    if i == 0:  # slips at once
        return theta0, -np.sign(np.sin(theta0) * (3 * np.cos(theta0) - 2 * c0))
    lo, hi = grid[i - 1], grid[i]
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if excess(mid) <= 0 else (lo, mid)
    f_needed = np.sin(lo) * (3 * np.cos(lo) - 2 * c0)
    return 0.5 * (lo + hi), (1.0 if f_needed < 0 else -1.0)  # forward if F < 0


pred = np.array([predicted(mu) for mu in mus])
err = np.max(np.abs(slip_theta[:n] - pred[:, 0]))
assert err < 1e-8, err
assert np.all(slip_dir[:n] == pred[:, 1])
print(f"largest difference simulated - closed form: {err:.1e} rad; directions all agree")

fig, ax = plt.subplots(figsize=(8, 4.5), layout="constrained")
fine = np.linspace(0.02, 1.2, 400)
curve = np.array([predicted(mu) for mu in fine])
for sign, color, name in ((-1.0, "tab:blue", "backward"), (1.0, "tab:orange", "forward")):
    part = np.where(curve[:, 1] == sign, np.degrees(curve[:, 0]), np.nan)
    ax.plot(fine, part, color=color, lw=1.5, label=f"closed form, {name}")
    sel = slip_dir[:n] == sign
    ax.plot(mus[sel], np.degrees(slip_theta[:n][sel]), "o", color=color, mfc="none", ms=6,
            label=f"simulated, tip slides {name}")
ax.axvline(r_max, color="0.5", ls=":", lw=1)
ax.text(r_max + 0.02, 12, rf"$\mu_s$ = {r_max:.3f}", fontsize=9)
ax.set(xlabel=r"static friction coefficient $\mu_s$", ylabel="slip angle (deg)",
       title="Where and which way the tip slips (rod released at 0.05 rad)")
ax.grid(alpha=0.3)
ax.legend(loc="lower right")
plt.show()"""),
    ("md", r"""
Below the peak ratio the tip slides backward early; above it the rod pivots past the sign change
of $F$ and slips forward, at 48° to 70° whatever the friction: with $\mu_s \to \infty$ the slip
angle tends to the 70.5° where $N$ of the pivoting rod vanishes."""),
    ("md", r"""
## Trajectories of the tip

A backward slip does not last: the rod's fall soon needs friction the other way, kinetic friction
brakes the tip, and the tip comes to rest. There the rod either sticks again (if the pivoting rod's
friction ratio is within $\mu_s$) or slides on the other way. The tip's position over time,
with the modes shaded, for a few runs of the sweep and the re-sticking run."""),
    ("code", r"""
def run_of(i, *keys):
    # Saved samples of run i up to its end (later samples are inf).
    ok = np.isfinite(res["ts"][i])
    return [res[k][i][ok] for k in keys]


def show(ax, i, label, color):
    t, x, mode = run_of(i, "ts", "tip_x", "mode")
    ax.plot(t, 100 * x, color=color, label=label)
    return t, x, mode


fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5), layout="constrained")
picks = [(int(np.argmin(np.abs(mus - mu))), c) for mu, c in
         ((0.1, "tab:blue"), (0.3, "tab:cyan"), (0.6, "tab:orange"), (1.0, "tab:red"))]
for i, color in picks:
    show(ax1, i, rf"$\mu_s$ = {mus[i]:.2f}", color)
ax1.set(xlabel="t (s)", ylabel="tip position x (cm)",
        title=r"Tip position ($\mu_k = 0.8\,\mu_s$, from 0.05 rad)")
ax1.legend(loc="upper left")
i = n + 2  # the re-sticking run
t, x, mode = show(ax2, i, r"$\mu_s$ = 0.365, $\mu_k$ = 0.3", "k")
for code, color, name in ((1, "tab:blue", "slip"), (0, "tab:green", "stick")):
    ax2.fill_between(t, 0, 1, where=(mode == code) & (t > 0.5), color=color, alpha=0.15,
                     transform=ax2.get_xaxis_transform(), label=name)
restick = (mode[1:] == 0) & (mode[:-1] == 1)
assert restick.any(), "the tip should stick again"
ax2.set(xlabel="t (s)", ylabel="tip position x (cm)", xlim=(0.75, t[-1]),
        title="Backward slip, re-stick, forward slip")
ax2.legend(loc="upper left")
for ax in (ax1, ax2):
    ax.grid(alpha=0.3)
plt.show()"""),
    ("md", r"""
## Energy: friction work, and the frictionless limit

Kinetic friction dissipates $\mu_k N |v_\text{tip}|$; the body integrates that work as a state
variable, and the invariant `energy` (mechanical energy plus friction work) must stay constant in
every mode. While the tip sticks, the friction force does no work (its point of application does
not move), so the mechanical energy itself is conserved. On a frictionless floor the run must
reproduce the falling rod on ice: its impact time is checked against the quadrature
`jd.FallingRod.fall_time`."""),
    ("code", r"""
scale = m * g * L / 2
drift = [np.max(np.abs(e[np.isfinite(e)] - e[0])) / scale for e in res["energy"]]
print(f"largest drift of mechanical energy + friction work over all runs: {max(drift):.1e}")
assert max(drift) < 1e-8

t, mech, work, mode = run_of(n + 2, "ts", "mechanical_energy", "friction_work", "mode")
stuck = (mode == 0) & (t > t[np.argmax(mode == 1)])  # stuck again after sliding
assert stuck.sum() >= 2 and np.ptp(mech[stuck]) < 1e-9 * scale

t_ice = float(jd.FallingRod(length=1.0, mass=1.0, g=9.81).fall_time(theta0))
t_free = float(res["t_final"][n + 1])
assert abs(t_free / t_ice - 1) < 1e-9, (t_free, t_ice)
print(f"frictionless floor: impact at {t_free:.12f} s, falling rod on ice {t_ice:.12f} s")

fig, ax = plt.subplots(figsize=(8, 4.3), layout="constrained")
ax.plot(t, 1e3 * (mech[0] - mech) / scale, color="tab:blue", lw=3, alpha=0.5,
        label="loss of mechanical energy")
ax.plot(t, 1e3 * work / scale, color="tab:red", ls="--", label="work against kinetic friction")
ax.fill_between(t, 0, 1, where=mode == 1, color="tab:blue", alpha=0.1,
                transform=ax.get_xaxis_transform(), label="tip slides")
ax.set(xlabel="t (s)", ylabel=r"energy / $(mgL/2)$ $\times 10^3$", xlim=(0.7, t[-1]),
       title=r"Energy balance, $\mu_s$ = 0.365, $\mu_k$ = 0.3 "
             f"(largest mismatch {max(drift):.0e})")
ax.grid(alpha=0.3)
ax.legend(loc="upper left")
plt.show()"""),
    ("md", r"""
## Lift-off

The normal force of a sliding rod is $N = m(g - \tfrac{L}{2}\dot\theta^2\cos\theta)/(1 +
3k\sin\theta)$, which vanishes where $L\dot\theta^2\cos\theta = 2g$ whatever the friction. A rod
falling away from upright never gets there ($L\dot\theta^2\cos\theta$ decreases at that point),
but a rod swung *towards* upright fast enough does: here one released at 0.8 rad turning at
$-5$ rad/s. It slips at once, lifts off, flies with a constant rate while its CM follows a
parabola, turns over in the air, and the run ends when its lower end (by then its top) touches
the floor (the impact itself would need a collision law, which this model does not have)."""),
    ("code", r"""
i = n
t, theta_l, mode, tip_x, tip_y, top_x, top_y = run_of(
    i, "ts", "theta", "mode", "tip_x", "tip_height", "top_x", "top_height")
assert res["y_final"]["liftoff"][i] == 1 and not res["flat"][i]
fly = mode == 2
t_lift = t[fly][0]
# Free flight: the rate is constant and the CM falls freely from the lift-off state.
rates = np.diff(theta_l[fly]) / np.diff(t[fly])
assert np.ptp(rates) < 1e-8 * np.abs(rates).max()
cm_y = 0.5 * (tip_y + top_y)[fly]
accel = np.diff(cm_y, 2) / np.diff(t[fly])[1:] ** 2
assert np.allclose(accel, -g, rtol=1e-6)
assert tip_y[fly].max() > 0.01 and tip_y.min() > -1e-12
print(f"slips at t = 0 (theta = {theta_l[0]:.2f} rad), lifts off at t = {t_lift:.4f} s "
      f"(theta = {theta_l[fly][0]:.3f} rad), touches down at t = {res['t_final'][i]:.4f} s; "
      f"highest tip {100 * tip_y.max():.1f} cm")

fig, ax = plt.subplots(figsize=(9, 4.5), layout="constrained")
colors = {0: "tab:green", 1: "tab:blue", 2: "tab:orange"}
for k in range(0, len(t), 16):
    ax.plot([100 * tip_x[k], 100 * top_x[k]], [100 * tip_y[k], 100 * top_y[k]],
            color=colors[int(mode[k])], lw=1.5, alpha=0.8)
ax.plot(100 * tip_x, 100 * tip_y, color="k", lw=1, label="path of the tip")
yf = {k: float(v[i]) for k, v in res["y_final"].items()}
end_x = yf["tip_x"] + np.array([0.0, L * np.sin(yf["theta"])])
end_y = yf["tip_y"] + np.array([0.0, L * np.cos(yf["theta"])])
assert abs(end_y.min()) < 1e-9  # its lower end (here the top) is on the floor
ax.plot(100 * end_x, 100 * end_y, color="tab:red", lw=2.5, label="touchdown")
for code, name in ((1, "sliding"), (2, "in flight")):
    ax.plot([], [], color=colors[code], label=f"rod, {name}")
ax.axhline(0, color="0.3", lw=2)
ax.set(xlabel="x (cm)", ylabel="height (cm)", aspect="equal",
       title=r"Swung towards upright at $-5$ rad/s from 0.8 rad: slide, lift-off, flight")
ax.legend(loc="lower right")
plt.show()"""),
]


if __name__ == "__main__":
    build(ROUGH, HERE / "08_rough_floor.ipynb")
