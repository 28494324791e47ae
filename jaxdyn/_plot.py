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
    elif kind == "rough-floor-rod":
        fig = _rough_rod(traj, plt)
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


def _rough_rod(traj, plt):
    body = traj.scene.body
    valid = np.asarray(traj.valid)
    out = {k: np.asarray(v)[valid] for k, v in traj.outputs().items()}
    t = np.asarray(traj.ts)[valid]
    mode = out["mode"]
    names = {0: "stick", 1: "slip", 2: "flight"}
    fig, ax = plt.subplots(1, 3, figsize=(14, 4))
    for a in ax:
        # Shade the modes: stick white, slip light blue, flight light orange.
        for code, color in ((1, "C0"), (2, "C1")):
            on = mode == code
            if on.any():
                a.fill_between(t, 0, 1, where=on, color=color, alpha=0.12, lw=0,
                               transform=a.get_xaxis_transform(), label=names[code])
    ax[0].plot(t, out["theta"], color="C0")
    ax[0].set(xlabel="t (s)", ylabel=r"$\theta$ (rad)", title="angle (shaded: slip / flight)")
    ax[0].legend(loc="upper left")
    weight = float(body.mass * body.g)
    ax[1].plot(t, out["normal_force"] / weight, color="C2", label="$N / mg$")
    ax[1].plot(t, np.abs(out["friction_force"]) / weight, color="C3", label="$|F| / mg$")
    ax[1].plot(t, float(body.mu_s) * out["normal_force"] / weight, color="0.4", ls="--",
               lw=1, label=r"$\mu_s N / mg$")
    ax[1].set(xlabel="t (s)", title="contact forces")
    ax[1].legend(loc="upper right")
    ax[2].plot(t, out["tip_x"], color="C4", label="tip")
    ax[2].plot(t, out["cm_x"], color="C5", ls="--", label="centre of mass")
    ax[2].set(xlabel="t (s)", ylabel="x (m)", title="horizontal positions")
    ax[2].legend(loc="upper left")
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


def plot_accuracy(results: dict, drift: dict | None, path: str) -> list[str]:
    """Work-precision diagram (log error against log wall time, a line per method, scipy dashed)
    and, if given, the invariant drift against time. Returns the files written."""
    import pathlib

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(results)
    cols = min(n, 2)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(6.2 * cols, 4.6 * rows), squeeze=False)
    for ax, (name, result) in zip(axes.ravel(), results.items()):
        # Points joined in sweep order (loose to tight), so each line walks down in error.
        for i, (method, points) in enumerate(result["methods"].items()):
            pts = [(p["wall_time"], p["error"]) for p in points if p["error"] > 0]
            if pts:
                ax.loglog(*zip(*pts), "o-", ms=3.5, lw=1.3, color=f"C{i}", label=method)
        for j, (method, points) in enumerate(result.get("scipy", {}).items()):
            pts = [(p["wall_time"], p["error"]) for p in points if p["error"] > 0]
            ax.loglog(*zip(*pts), "s--", ms=3.5, lw=1.2, color="0.35" if j else "0.6",
                      label=f"scipy {method}")
        ax.set(xlabel="wall time per solve (s)", ylabel="error against the reference",
               title=f"{name}: {result['description']}")
        ax.title.set_fontsize(9)
        ax.grid(alpha=0.3, which="major")
        ax.legend(fontsize=7, ncol=2)
    for ax in axes.ravel()[n:]:
        ax.set_visible(False)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written = [path]
    if drift is not None:
        p = pathlib.Path(path)
        drift_path = str(p.with_name(p.stem + "_drift" + p.suffix))
        fig, axes = plt.subplots(1, 2, figsize=(12.5, 4.3))
        t = np.asarray(drift["t"])
        for i, (name, series) in enumerate(drift["series"].items()):
            for ax, key in zip(axes, ("energy", "momentum")):
                v = np.asarray(series[key])
                ax.loglog(t[1:], np.maximum(v[1:], 1e-17), lw=1.2, color=f"C{i}", label=name)
        for ax, key in zip(axes, ("energy", "|H|")):
            ax.set(xlabel="time", ylabel=f"relative {key} error",
                   title=f"Drift of {key} over a long horizon")
            ax.grid(alpha=0.3, which="major")
            ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(drift_path, dpi=110)
        plt.close(fig)
        written.append(drift_path)
    return written
