"""Collagen fibre directions from a mesh sidecar's ``fibres`` spec (pure numpy).

Rule ``spherical_cap`` (the cornea, after the thesis' Fig. 2.3): two fibre
families tangent to the spherical surfaces, one following ``m_axis``
(nasal-temporal), one following ``n_axis`` (superior-inferior), each being
its axis with the component along the local outward normal removed:

    nrm = normalise(x - centre)
    m0  = normalise(m_axis - (m_axis . nrm) nrm)
    n0  = normalise(n_axis - (n_axis . nrm) nrm)

At the apex (nrm perpendicular to both axes) the families are orthogonal;
away from it they are roughly so.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from hapticrom.shared.errors import InputError

RULES = ("spherical_cap",)


def _vector(spec: Mapping[str, Any], key: str) -> np.ndarray:
    try:
        vector = np.asarray(spec[key], dtype=np.float64)
    except KeyError:
        raise InputError(f"fibre spec lacks {key!r}") from None
    except (TypeError, ValueError):
        raise InputError(f"fibre spec {key!r} must be three numbers") from None
    if vector.shape != (3,) or not np.all(np.isfinite(vector)):
        raise InputError(f"fibre spec {key!r} must be three finite numbers, got {spec[key]!r}")
    return vector


def _tangent_unit(axis: np.ndarray, normal: np.ndarray, name: str) -> np.ndarray:
    tangent = axis - (normal @ axis)[:, None] * normal
    length = np.linalg.norm(tangent, axis=1)
    if np.any(length < 1e-12 * np.linalg.norm(axis)):
        raise InputError(f"fibre direction {name} is undefined where the normal is along it")
    return tangent / length[:, None]


def fibre_directions(
    spec: Mapping[str, Any] | None, x: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Unit fibre directions ``(m0, n0)``, each (n, 3), at points ``x`` (n, 3) in mm."""
    if spec is None:
        raise InputError("this mesh has no fibres (its sidecar says fibres: null)")
    if not isinstance(spec, Mapping):
        raise InputError(f"fibre spec must be a mapping, got {type(spec).__name__}")
    rule = spec.get("rule")
    if rule not in RULES:
        raise InputError(f"unknown fibre rule {rule!r}; known: {', '.join(RULES)}")
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise InputError(f"fibre points must be an (n, 3) array, got shape {x.shape}")

    centre = _vector(spec, "centre")
    radial = x - centre
    distance = np.linalg.norm(radial, axis=1)
    if np.any(distance == 0.0):
        raise InputError("fibre directions are undefined at the spherical cap's centre")
    normal = radial / distance[:, None]
    m0 = _tangent_unit(_vector(spec, "m_axis"), normal, "m_axis")
    n0 = _tangent_unit(_vector(spec, "n_axis"), normal, "n_axis")
    return m0, n0
