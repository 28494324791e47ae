"""Animations of a run: the body turning in space, or the rod sliding on the ice."""

from typing import Any

import numpy as np

from ._errors import ParameterError


def animate(traj, *, frames: int = 120, interval: float = 40.0, trail: bool = True,
            title: str | None = None) -> Any:
    """Animate a run with matplotlib.

    A rigid body is drawn as the uniform box with its principal moments (edge lengths from
    the moments), its principal axes (red, green, blue for the smallest to the largest moment)
    and the angular-momentum vector (black), fixed in space for a torque-free body, in the
    inertial frame; the tip of the body's largest-moment axis leaves a trail. The falling rod
    is drawn from the side, sliding on the ice, with its centre of mass and the path of its
    tip. The run needs its saved samples (`ts=...`); a rigid body needs its attitude
    (`Scene(..., attitude=True)`).

    **Arguments:**

    - `traj`: a [`jaxdyn.Trajectory`][].
    - `frames`: number of frames, evenly spaced in time over the samples reached.
    - `interval`: milliseconds between frames.
    - `trail`: draw the path of the largest axis's tip (rigid body) or of the rod's tip.
    - `title`: the figure's title (default: the body and the span).

    **Returns:**

    A `matplotlib.animation.FuncAnimation`: `.to_jshtml()` gives an HTML5 animation for a
    notebook (`IPython.display.HTML`), `.save("flip.gif", writer="pillow")` a GIF
    (`.mp4` needs ffmpeg).
    """
    import matplotlib.pyplot as plt

    valid = np.asarray(traj.valid)
    t = np.asarray(traj.ts)[valid]
    if t.size < 2:
        raise ParameterError("animate needs the run's samples: simulate(..., ts=...) with two "
                             "or more times")
    if not isinstance(frames, int) or frames < 2:
        raise ParameterError(f"frames={frames!r}: must be an integer of at least 2")
    pick = np.unique(np.searchsorted(t, np.linspace(t[0], t[-1], frames)).clip(0, t.size - 1))
    out = {k: np.asarray(v)[valid][pick] for k, v in traj.outputs().items()}
    kind = traj.scene.body.kind
    title = title or f"{kind}, t = {t[0]:g} to {t[-1]:g} s"
    if "quaternion" in out and "omega" in out:
        return _rigid(traj, out, t[pick], interval, trail, title, plt)
    if "tip_x" in out and "top_x" in out:
        return _rod(out, t[pick], interval, trail, title, plt)
    raise ParameterError(
        "animate needs the attitude of a rigid body (Scene(..., attitude=True)) or a rod")


def _box(moments: np.ndarray) -> np.ndarray:
    """Half edge lengths of the uniform box with these principal moments (up to a scale):
    `I_1 ∝ b^2 + c^2`, ..., so `a^2 ∝ I_2 + I_3 - I_1`."""
    i1, i2, i3 = moments
    half = np.sqrt(np.maximum([i2 + i3 - i1, i1 + i3 - i2, i1 + i2 - i3], 1e-3 * max(moments)))
    return half / half.max()


_EDGES = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]


def _rigid(traj, out, t, interval, trail, title, plt):
    from matplotlib import animation

    body = traj.scene.body
    moments = np.asarray(body.principal_moments)
    axes_body = np.asarray(body.principal_axes)  # columns: principal axes in the body frame
    order = np.argsort(moments)
    half = _box(moments)
    corners = np.array([[(1 if c & 1 else -1) * half[0], (1 if c & 2 else -1) * half[1],
                         (1 if c & 4 else -1) * half[2]] for c in range(8)])
    corners = corners @ axes_body.T  # the box along the principal axes, in the body frame
    rot = out["dcm"]  # body-to-inertial rotation of each frame
    if rot.shape[-2:] != (3, 3):  # pragma: no cover - every attitude scene outputs it
        raise ParameterError("animate needs the rotation matrix output 'dcm'")
    h = out.get("momentum_inertial")
    h_dir = None if h is None else h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True),
                                                  1e-300)

    fig = plt.figure(figsize=(5.2, 5.2))
    ax = fig.add_subplot(projection="3d")
    ax.set(xlim=(-1.3, 1.3), ylim=(-1.3, 1.3), zlim=(-1.3, 1.3), xlabel="x", ylabel="y",
           zlabel="z")
    ax.set_box_aspect((1, 1, 1))
    ax.set_title(title, fontsize=9)
    edges = [ax.plot([], [], [], color="0.35", lw=1.2)[0] for _ in _EDGES]
    colors = ("tab:red", "tab:green", "tab:blue")
    axis_lines = [ax.plot([], [], [], color=c, lw=2.5)[0] for c in colors]
    h_line = ax.plot([], [], [], color="k", lw=2.0, label="angular momentum H")[0]
    path = ax.plot([], [], [], color="tab:blue", lw=0.8, alpha=0.6)[0]
    label = ax.text2D(0.02, 0.95, "", transform=ax.transAxes, fontsize=9)
    ax.legend(handles=[h_line, *axis_lines],
              labels=["H (fixed in space)", "smallest moment", "middle", "largest"],
              loc="lower left", fontsize=7)
    tip = []

    def draw(k):
        r = rot[k]
        pts = corners @ r.T
        for line, (a, b) in zip(edges, _EDGES):
            line.set_data_3d(pts[[a, b], 0], pts[[a, b], 1], pts[[a, b], 2])
        for line, i in zip(axis_lines, order):
            v = r @ axes_body[:, i] * 1.25
            line.set_data_3d([0, v[0]], [0, v[1]], [0, v[2]])
        if h_dir is not None:
            v = h_dir[k] * 1.3
            h_line.set_data_3d([0, v[0]], [0, v[1]], [0, v[2]])
        if trail:
            if k == 0:
                tip.clear()
            tip.append(r @ axes_body[:, order[-1]] * 1.25)
            p = np.array(tip)
            path.set_data_3d(p[:, 0], p[:, 1], p[:, 2])
        label.set_text(f"t = {t[k]:.2f} s")
        return [*edges, *axis_lines, h_line, path, label]

    anim = animation.FuncAnimation(fig, draw, frames=len(t), interval=interval, blit=False)
    plt.close(fig)
    return anim


def _rod(out, t, interval, trail, title, plt):
    from matplotlib import animation

    tip_x, top_x, top_y = out["tip_x"], out["top_x"], out["top_height"]
    tip_y = out.get("tip_height", np.zeros_like(tip_x))
    cm_x, cm_y = out["cm_x"], out["cm_height"]
    length = float(np.hypot(top_x[0] - tip_x[0], top_y[0] - tip_y[0]))
    fig, ax = plt.subplots(figsize=(7.6, 4.0))
    lo = min(tip_x.min(), top_x.min()) - 0.1 * length
    hi = max(tip_x.max(), top_x.max()) + 0.1 * length
    ax.set(xlim=(lo, hi), ylim=(-0.08 * length, 1.1 * length), xlabel="x (m)",
           ylabel="height (m)", aspect="equal")
    ax.set_title(title, fontsize=9)
    ax.axhspan(-0.08 * length, 0.0, color="#cfe8f7")  # the ice
    ax.axhline(0.0, color="#5fa8d3", lw=1.5)
    ax.plot(cm_x, cm_y, color="0.6", lw=0.8, ls=":", label="centre of mass path")
    rod_line = ax.plot([], [], color="tab:brown", lw=4, solid_capstyle="round")[0]
    cm = ax.plot([], [], "o", color="k", ms=5, label="centre of mass")[0]
    path = ax.plot([], [], color="tab:blue", lw=1.0, label="tip path")[0]
    label = ax.text(0.02, 0.92, "", transform=ax.transAxes, fontsize=9)
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=7)
    fig.tight_layout()

    def draw(k):
        rod_line.set_data([tip_x[k], top_x[k]], [tip_y[k], top_y[k]])
        cm.set_data([cm_x[k]], [cm_y[k]])
        if trail:
            path.set_data(tip_x[: k + 1], tip_y[: k + 1])
        label.set_text(f"t = {t[k]:.3f} s")
        return [rod_line, cm, path, label]

    anim = animation.FuncAnimation(fig, draw, frames=len(t), interval=interval, blit=False)
    plt.close(fig)
    return anim
