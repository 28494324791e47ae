"""`jaxdyn separatrix`: relative equilibria, separatrix energies and critical rotor momenta."""

import math
from typing import Any

from ._common import emit, enable_x64

HELP = "relative equilibria and separatrix energies of a body or gyrostat; critical rotor momenta"
LAPACK = True  # (its programs solve linear systems: `jaxdyn._xla`)


def add_arguments(parser) -> None:
    parser.add_argument("--inertia", required=True, metavar="I1,I2,I3",
                        help="principal moments of inertia (kg m^2)")
    parser.add_argument("--rotor", metavar="HX,HY,HZ",
                        help="constant rotor momentum in the body frame (kg m^2/s); "
                             "default: no rotor")
    parser.add_argument("--momentum", metavar="H",
                        help="total angular momentum |I w + h| of the sphere (default 1)")
    parser.add_argument("--critical-rotor", action="store_true",
                        help="instead: the rotor momenta along --spin-axis at which a spin of "
                             "--rate about that axis changes stability")
    parser.add_argument("--spin-axis", metavar="K",
                        help="with --critical-rotor: the spin axis, 1, 2 or 3 (order of --inertia)")
    parser.add_argument("--rate", metavar="W", help="with --critical-rotor: spin rate (rad/s)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")


_ROUNDOFF = 1e-14  # relative: smaller components are round-off around an exact zero


def _clean(x, tol: float) -> float:
    return 0.0 if abs(float(x)) < tol else float(x)


def _numbers(field: str, text: str, count: int | None = None) -> list[float]:
    from .._validation import ParameterError

    what = f"{count} comma-separated numbers" if count else "a number"
    try:
        values = [float(part) for part in text.split(",")]
    except ValueError:
        values = []
    if not values or (count is not None and len(values) != count) or (
        count is None and len(values) != 1
    ):
        raise ParameterError(f"{field}={text!r}: expected {what}")
    if not all(math.isfinite(v) for v in values):
        raise ParameterError(f"{field}={text!r}: expected finite numbers")
    return values


def _reject(args, names: list[str], reason: str) -> None:
    from .._validation import ParameterError

    for name in names:
        if getattr(args, name.lstrip("-").replace("-", "_")) is not None:
            raise ParameterError(f"{name}: {reason}")


def _critical(args, inertia: list[float]) -> dict[str, Any]:
    import numpy as np

    from .._separatrix import critical_rotor_momenta
    from .._validation import ParameterError

    _reject(args, ["--rotor", "--momentum"],
            "not used with --critical-rotor (the rotor momentum is what is solved for)")
    if args.spin_axis is None:
        raise ParameterError("--spin-axis is required with --critical-rotor: 1, 2 or 3")
    if args.spin_axis.strip() not in ("1", "2", "3"):
        raise ParameterError(f"--spin-axis={args.spin_axis!r}: must be 1, 2 or 3 "
                             "(the axis in the order of --inertia)")
    if args.rate is None:
        raise ParameterError("--rate is required with --critical-rotor: the spin rate in rad/s")
    (rate,) = _numbers("--rate", args.rate)
    if rate == 0:
        raise ParameterError("--rate=0: must be nonzero (a spin at rate 0 has no stability "
                             "to change)")
    axis = int(args.spin_axis)
    roots = critical_rotor_momenta(np.asarray(inertia, np.float64), axis - 1, rate)
    return {
        "inertia": inertia,
        "spin_axis": axis,
        "rate": rate,
        "critical_rotor_momenta": np.asarray(roots).tolist(),
    }


def _equilibria(args, inertia: list[float]) -> dict[str, Any]:
    import numpy as np

    from .._effects import Rotor
    from .._rigid_body import RigidBody
    from .._scene import Scene
    from .._separatrix import find_equilibria
    from .._validation import ParameterError

    _reject(args, ["--spin-axis", "--rate"], "only used with --critical-rotor")
    rotor = None if args.rotor is None else _numbers("--rotor", args.rotor, 3)
    momentum = 1.0 if args.momentum is None else _numbers("--momentum", args.momentum)[0]
    if not momentum > 0:
        raise ParameterError(f"--momentum={args.momentum}: must be positive")
    body = RigidBody(np.asarray(inertia, np.float64))
    effects = () if rotor is None else (Rotor(np.asarray(rotor, np.float64)),)
    eq = find_equilibria(Scene(body, effects), momentum)
    omega, energy = np.asarray(eq.omega), np.asarray(eq.energy)
    eig = np.asarray(eq.eigenvalues)
    # Round-off (components ~1e-40 where the exact value is zero) is printed as 0.
    w_tol = _ROUNDOFF * max(float(np.max(np.abs(omega), initial=0.0)), 1e-300)
    e_tol = _ROUNDOFF * max(float(np.max(np.abs(eig), initial=0.0)), 1e-300)
    out: dict[str, Any] = {
        "inertia": inertia,
        "rotor": rotor if rotor is not None else [0.0, 0.0, 0.0],
        "momentum": momentum,
        "equilibria": [
            {
                "omega": [_clean(x, w_tol) for x in omega[i]],
                "energy": float(energy[i]),
                "kind": eq.kind[i],
                "eigenvalues": [[_clean(z.real, e_tol), _clean(z.imag, e_tol)] for z in eig[i]],
            }
            for i in range(len(eq))
        ],
        "separatrix_energies": np.asarray(eq.separatrix_energies).tolist(),
    }
    if eq.continuum:
        out["degenerate_equilibria"] = int(eq.degenerate.shape[0])
        out["note"] = (
            "equilibria with a degenerate linearisation were found (a continuum of equilibria, "
            "as for two equal principal moments, or a bifurcation point): they are neither "
            "saddles nor centres and give no isolated separatrix"
        )
    return out


def run(args) -> int:
    enable_x64()
    inertia = _numbers("--inertia", args.inertia, 3)
    if args.critical_rotor:
        out = _critical(args, inertia)
        title = f"critical rotor momenta along axis {out['spin_axis']}"
    else:
        out = _equilibria(args, inertia)
        title = f"relative equilibria on the momentum sphere |H| = {out['momentum']:g}"
    emit(out, args.json, title=title)
    return 0
