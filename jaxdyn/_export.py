"""Results out the way people analyse them: xarray datasets and pandas data frames.

pandas and xarray are optional (`pip install "jaxdyn[data]"`); they are imported when an
exporter is called. Array-valued quantities are split into components: in a data frame as
columns `omega[0]`, `omega[1]`, ...; in a dataset as a variable with a dimension per axis
(`omega_dim0`). The values an ensemble varied are named `varied.<name>` beside the observed
ones (`varied.omega[0]`, the initial rate drawn; `omega[0]`, the final rate observed).
"""

from collections.abc import Mapping
from typing import Any

import numpy as np

from ._errors import ParameterError


def _need(module: str):
    import importlib

    try:
        return importlib.import_module(module)
    except ModuleNotFoundError:
        raise ParameterError(f"{module} is not installed: pip install 'jaxdyn[data]'") from None


def _columns(values: Mapping[str, Any], n: int) -> dict[str, np.ndarray]:
    """name -> (n, ...) arrays as flat columns (`name[i]`, `name[i,j]`)."""
    out = {}
    for name, value in values.items():
        a = np.asarray(value)
        if a.ndim == 1:
            out[name] = a
            continue
        flat = a.reshape(n, -1)
        for j, index in enumerate(np.ndindex(*a.shape[1:])):
            out[f"{name}[{','.join(map(str, index))}]"] = flat[:, j]
    return out


def _variables(values: Mapping[str, Any], dim: str, units: Mapping[str, str]):
    out = {}
    for name, value in values.items():
        a = np.asarray(value)
        dims = (dim,) + tuple(f"{name}_dim{i}" for i in range(a.ndim - 1))
        attrs = {"units": units[name]} if units.get(name) else {}
        out[name] = (dims, a, attrs)
    return out


def _samples(traj) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The times reached, and every state variable and derived output at them."""
    valid = np.asarray(traj.valid)
    outputs = {k: np.asarray(v)[valid] for k, v in traj.outputs().items()}
    states = {k: np.asarray(v)[valid] for k, v in traj.ys.items() if k not in outputs}
    return np.asarray(traj.ts)[valid], {**states, **outputs}


def trajectory_to_xarray(traj, units: Mapping[str, str]):
    """See [`jaxdyn.Trajectory.to_xarray`][]."""
    xr = _need("xarray")
    t, values = _samples(traj)
    data = _variables(values, "t", units)
    return xr.Dataset(data, coords={"t": ("t", t, {"units": "s"})},
                      attrs={"outcome": traj.outcome_name, "t_final": float(traj.t_final),
                             "body": traj.scene.body.kind,
                             "effects": ",".join(traj.scene.labels)})


def trajectory_to_dataframe(traj):
    """See [`jaxdyn.Trajectory.to_dataframe`][]."""
    pd = _need("pandas")
    t, values = _samples(traj)
    return pd.DataFrame(_columns(values, t.size), index=pd.Index(t, name="t"))


def write(obj, path: str) -> None:
    """Write a `Trajectory` or an `Ensemble` as CSV (`.csv`, one row per sample or per
    trajectory) or NetCDF (`.nc`, the xarray dataset; scipy's NetCDF-3 writer)."""
    if path.lower().endswith(".csv"):
        obj.to_dataframe().to_csv(path)
    else:
        obj.to_xarray().to_netcdf(path, engine="scipy")


def ensemble_to_dataframe(ens):
    """See [`jaxdyn.Ensemble.to_dataframe`][]."""
    pd = _need("pandas")
    n = ens.n
    frame = {"status": np.asarray(ens.status_names)[ens.status], "steps": ens.steps}
    frame.update(_columns({f"varied.{k}": v for k, v in ens.varied().items()}, n))
    frame.update(_columns(ens.values, n))
    df = pd.DataFrame(frame)
    df.index.name = "trajectory"
    return df


def ensemble_to_xarray(ens):
    """See [`jaxdyn.Ensemble.to_xarray`][]."""
    xr = _need("xarray")
    varied = ens.varied()
    data = _variables({f"varied.{k}": v for k, v in varied.items()}, "trajectory", {})
    data.update(_variables(ens.values, "trajectory", {}))
    data["status"] = (("trajectory",), np.asarray(ens.status_names)[ens.status])
    data["steps"] = (("trajectory",), ens.steps)
    return xr.Dataset(data, coords={"trajectory": np.arange(ens.n)},
                      # (not "mode": scipy's NetCDF writer keeps its file mode there)
                      attrs={"varied": ",".join(varied), "ensemble_mode": ens.mode})
