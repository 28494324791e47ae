"""Exports to pandas and xarray: an exported ensemble read back equals the original, and the
varied values it lists are the ones each trajectory ran with (checked by rerunning one)."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxdyn as jd

pd = pytest.importorskip("pandas")
xr = pytest.importorskip("xarray")

INERTIA = [1.0, 2.0, 2.5]


@pytest.fixture(scope="module")
def ensemble():
    scene = jd.Scene(jd.RigidBody(INERTIA))
    y0 = scene.state(omega=[1e-3, 1.0, 1e-3])
    res = jd.ensemble(scene, y0, 5.0, n=24, key=7,
                      vary={"inertia": jd.LogNormal(INERTIA, 0.01),
                            "omega[0]": jd.Normal(0.0, 1e-3)})
    return scene, y0, res


def test_dataframe_round_trip_and_the_varied_values_are_the_ones_run(ensemble, tmp_path):
    scene, y0, res = ensemble
    df = res.to_dataframe()
    assert len(df) == 24 and list(df.columns[:2]) == ["status", "steps"]
    for col in ("varied.inertia[0]", "varied.inertia[2]", "varied.omega[0]", "energy",
                "omega[0]"):
        assert col in df.columns
    path = tmp_path / "ensemble.csv"
    df.to_csv(path)
    back = pd.read_csv(path, index_col="trajectory")
    pd.testing.assert_frame_equal(back, df, check_exact=False, rtol=1e-15, check_dtype=False)
    # Rerun trajectory 5 alone with the values the frame lists: the same observed rates.
    i = 5
    inertia = [df.loc[i, f"varied.inertia[{j}]"] for j in range(3)]
    omega0 = np.asarray(y0["omega"]).copy()
    omega0[0] = df.loc[i, "varied.omega[0]"]
    s = scene.replace(inertia=jnp.asarray(inertia))
    traj = jd.simulate(s, s.state(omega=omega0), 5.0)
    assert np.allclose(np.asarray(traj.y_final["omega"]), df.loc[i, ["omega[0]", "omega[1]",
                                                                      "omega[2]"]].to_numpy(),
                       rtol=1e-6, atol=1e-9)


def test_xarray_round_trip_through_netcdf(ensemble, tmp_path):
    _, _, res = ensemble
    ds = res.to_xarray()
    assert ds.sizes["trajectory"] == 24
    assert ds["omega"].dims == ("trajectory", "omega_dim0")
    path = tmp_path / "ensemble.nc"
    ds.to_netcdf(str(path), engine="scipy")
    back = xr.open_dataset(str(path), engine="scipy").load()
    xr.testing.assert_allclose(back.drop_vars("status"), ds.drop_vars("status"))
    assert list(back["status"].values) == list(ds["status"].values)


def test_trajectory_to_xarray_with_units():
    rod = jd.FallingRod(length=1.0, mass=1.0, g=9.81)
    scene = jd.Scene(rod)
    traj = jd.simulate(scene, scene.state(theta=0.1), 5.0, ts=jnp.linspace(0.0, 5.0, 51))
    ds = traj.to_xarray()
    valid = np.asarray(traj.valid)
    assert np.array_equal(ds["t"].values, np.asarray(traj.ts)[valid])  # samples before impact
    assert ds["normal_force"].attrs["units"] == "N" and ds["theta"].attrs["units"] == "rad"
    assert np.allclose(ds["normal_force"].values, np.asarray(traj.normal_force)[valid])
    assert ds.attrs["outcome"] == "event"


def test_commands_write_csv_and_netcdf(tmp_path, capsys):
    from jaxdyn._cli import main

    run_csv = tmp_path / "run.csv"
    assert main(["run", "--samples", "21", "--export", str(run_csv), "--json"]) == 0
    df = pd.read_csv(run_csv, index_col="t")
    assert len(df) >= 2 and "normal_force" in df.columns and "theta" in df.columns
    mc_nc = tmp_path / "mc.nc"
    assert main(["montecarlo", "torque-free", "--n", "16", "--t1", "2", "--export", str(mc_nc),
                 "--vary", "omega[0]+=normal(0, 1e-3)", "--json"]) == 0
    ds = xr.open_dataset(str(mc_nc), engine="scipy").load()
    assert ds.sizes["trajectory"] == 16 and "varied.omega[0]" in ds
    mc_csv = tmp_path / "mc.csv"
    assert main(["montecarlo", "torque-free", "--n", "16", "--t1", "2", "--export", str(mc_csv),
                 "--vary", "omega[0]+=normal(0, 1e-3)", "--json"]) == 0
    back = pd.read_csv(mc_csv, index_col="trajectory")
    assert np.allclose(back["varied.omega[0]"], ds["varied.omega[0]"].values, rtol=1e-15)
    with pytest.raises(SystemExit) as err:
        main(["run", "--export", str(tmp_path / "run.txt")])
    assert err.value.code == 2
    capsys.readouterr()


def test_a_run_written_to_a_directory_reads_back_as_the_ensemble(tmp_path, capsys):
    """`jd.Ensemble.read(DIR)` on the chunk files of a run (three chunks here): the same
    statuses, steps, kept values, statistics and varied values as the run returned, so its
    data frame is the same; the command's `--out` directory reads the same way. A directory
    whose run has not finished is refused, naming the missing chunk."""
    scene = jd.Scene(jd.RigidBody(INERTIA))
    y0 = scene.state(omega=[1e-3, 1.0, 1e-3])
    out = tmp_path / "run"
    res = jd.ensemble(scene, y0, 5.0, n=40, key=3, chunk_size=16, out=out,
                      vary={"inertia": jd.LogNormal(INERTIA, 0.01)})
    back = jd.Ensemble.read(out)
    assert back.n == res.n and np.array_equal(back.status, res.status)
    assert np.array_equal(back.steps, res.steps)
    for k, v in res.values.items():
        assert np.array_equal(back.values[k], v)
    for k, stats in res.statistics.items():
        for f in ("count", "mean", "std", "min", "max"):
            assert np.allclose(back.statistics[k][f], stats[f], rtol=1e-14, atol=0)
    pd.testing.assert_frame_equal(back.to_dataframe(), res.to_dataframe())
    (out / "chunk-000001.npz").unlink()
    with pytest.raises(jd.ParameterError, match=r"chunk\(s\) \[1\] of 3"):
        jd.Ensemble.read(out)
    with pytest.raises(jd.ParameterError, match="no run.json"):
        jd.Ensemble.read(tmp_path)

    from test_cli import run_cli

    status, _, err = run_cli(capsys, "montecarlo", "intermediate-axis", "--n", "24",
                             "--out", str(tmp_path / "cli"), "--vary", "omega[0]=normal(0,1e-3)")
    assert status == 0, err
    frame = jd.Ensemble.read(tmp_path / "cli").to_dataframe()
    assert len(frame) == 24 and "varied.omega[0]" in frame.columns
