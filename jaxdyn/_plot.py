"""Figures for `jaxdyn run --plot` (matplotlib, imported only when a plot is asked for)."""

import numpy as np


def plot_trajectory(traj, path: str, title: str = "") -> None:
    """Write a PNG summarising a run: per body kind, the figures a reader looks for first."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kind = traj.scene.body.kind
    if kind == "falling-rod":
        fig = _rod(traj, plt)
    else:
        fig = _rigid(traj, plt)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _rod(traj, plt):
    body = traj.scene.body
    valid = np.asarray(traj.valid)
    out = {k: np.asarray(v)[valid] for k, v in traj.outputs().items()}
    t = np.asarray(traj.ts)[valid]
    theta0, theta_dot0 = out["theta"][0], out["theta_dot"][0]
    fig, ax = plt.subplots(1, 3, figsize=(13, 4))
    ax[0].plot(t, out["theta"], color="C0")
    ax[0].axhline(np.sign(out["theta"][-1]) * np.pi / 2, color="0.6", ls=":", lw=1)
    ax[0].set(xlabel="t (s)", ylabel=r"$\theta$ (rad)", title="angle from the vertical")
    grid = np.linspace(theta0, np.sign(out["theta"][-1] or 1) * np.pi / 2, 400)
    exact = np.asarray(body.rate(grid, theta0, theta_dot0))
    ax[1].plot(grid, exact, color="0.3", lw=3, alpha=0.4, label="energy integral")
    ax[1].plot(out["theta"], np.abs(out["theta_dot"]), color="C1", lw=1.2, label="simulated")
    ax[1].set(xlabel=r"$\theta$ (rad)", ylabel=r"$|\dot\theta|$ (rad/s)",
              title=r"rate against angle")
    ax[1].legend()
    ax[2].plot(out["theta"], out["normal_force_over_weight"], color="C2")
    ax[2].axhline(1.0, color="0.6", ls=":", lw=1)
    ax[2].set(xlabel=r"$\theta$ (rad)", ylabel=r"$N / (m g)$", title="normal force")
    return fig


def _rigid(traj, plt):
    valid = np.asarray(traj.valid)
    out = {k: np.asarray(v)[valid] for k, v in traj.outputs().items()}
    t = np.asarray(traj.ts)[valid]
    fig = plt.figure(figsize=(12, 4.8))
    ax = fig.add_subplot(1, 2, 1)
    for i in range(3):
        ax.plot(t, out["omega"][:, i], label=rf"$\omega_{i + 1}$")
    ax.set(xlabel="t (s)", ylabel="body rate (rad/s)", title="body rates")
    ax.legend()
    ax3 = fig.add_subplot(1, 2, 2, projection="3d")
    h = out["angular_momentum"]
    radius = np.linalg.norm(h[0])
    u, v = np.mgrid[0 : 2 * np.pi : 40j, 0 : np.pi : 20j]
    ax3.plot_wireframe(radius * np.cos(u) * np.sin(v), radius * np.sin(u) * np.sin(v),
                       radius * np.cos(v), color="0.85", lw=0.5)
    ax3.plot(h[:, 0], h[:, 1], h[:, 2], color="C3", lw=1.5)
    ax3.set(xlabel="$h_1$", ylabel="$h_2$", zlabel="$h_3$",
            title="polhode on the momentum sphere (body frame)")
    ax3.set_box_aspect((1, 1, 1))
    return fig
