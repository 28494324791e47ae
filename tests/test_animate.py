"""jd.animate: the body turns as the run says, the angular momentum stays fixed in space, the
rod slides on the ice; animations save as GIF, and the command writes one."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn as jd

pytest.importorskip("matplotlib")
# Frames are drawn by hand here, not rendered to a movie: matplotlib's notice is expected.
pytestmark = pytest.mark.filterwarnings("ignore:Animation was deleted without rendering")


def test_rigid_body_turns_with_its_attitude_and_h_stays_fixed(tmp_path):
    scene = jd.Scene(jd.RigidBody([1.0, 2.0, 3.0]), attitude=True)
    traj = jd.simulate(scene, scene.state(omega=[1e-3, 2.0, 1e-3]), 20.0,
                       ts=jnp.linspace(0.0, 20.0, 401))
    anim = jd.animate(traj, frames=12)
    ax = anim._fig.axes[0]
    h_line = next(line for line in ax.lines if line.get_label() == "angular momentum H")
    largest = next(line for line in ax.lines  # the largest-moment axis: blue, thick
                   if line.get_color() == "tab:blue" and line.get_linewidth() == 2.5)
    directions, axes_drawn = [], []
    for k in range(12):
        anim._func(k)
        x, y, z = h_line.get_data_3d()
        directions.append(np.array([x[1], y[1], z[1]]))
        x, y, z = largest.get_data_3d()
        axes_drawn.append(np.array([x[1], y[1], z[1]]) / 1.25)
    directions = np.array(directions)
    assert np.max(np.abs(directions - directions[0])) < 1e-6  # H fixed in space
    # The drawn axis is the body's third axis rotated by the run's attitude.
    valid = np.asarray(traj.ts)
    pick = np.searchsorted(valid, np.linspace(0.0, 20.0, 12))
    expected = np.asarray(jnp.stack([jd.quat_rotate(q, jnp.array([0.0, 0.0, 1.0]))
                                     for q in traj.ys["quaternion"][pick]]))
    assert np.allclose(np.array(axes_drawn), expected, atol=1e-12)
    path = tmp_path / "flip.gif"
    anim.save(path, writer="pillow", dpi=40)
    assert path.stat().st_size > 1000


def test_rod_slides_on_the_ice():
    rod = jd.FallingRod(length=1.0)
    scene = jd.Scene(rod)
    traj = jd.simulate(scene, scene.state(theta=0.1), 5.0, ts=jnp.linspace(0.0, 5.0, 501))
    anim = jd.animate(traj, frames=20)
    ax = anim._fig.axes[0]
    rod_line = next(line for line in ax.lines if line.get_linewidth() == 4)
    for k in range(20):
        anim._func(k)
        (x0, x1), (y0, y1) = rod_line.get_data()
        assert y0 == 0.0  # the tip stays on the ice
        assert np.isclose(np.hypot(x1 - x0, y1 - y0), 1.0)  # a rigid rod of length L


def test_animate_refuses_what_it_cannot_draw():
    scene = jd.Scene(jd.RigidBody([1.0, 2.0, 3.0]))  # no attitude
    traj = jd.simulate(scene, scene.state(omega=[0.1, 1.0, 0.1]), 1.0,
                       ts=jnp.linspace(0.0, 1.0, 11))
    with pytest.raises(jd.ParameterError, match="attitude"):
        jd.animate(traj)
    with pytest.raises(jd.ParameterError, match="frames"):
        jd.animate(traj, frames=1)


def test_command_writes_a_gif(tmp_path, capsys):
    from jaxdyn._cli import main

    path = tmp_path / "flip.gif"
    assert main(["run", "intermediate-axis", "--t1", "5", "--samples", "11", "--animate",
                 str(path), "--json"]) == 0
    assert path.stat().st_size > 1000
    with pytest.raises(SystemExit) as err:
        main(["run", "--animate", str(tmp_path / "flip.png")])
    assert err.value.code == 2
    capsys.readouterr()
