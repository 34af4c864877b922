"""Eager input checks of the box-QP projection: shapes always, values when they are concrete."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxlimits._src.tracing import is_traced


def _array(name, value, dtype=None):
    if value is None:
        return None
    try:
        arr = jnp.asarray(value) if dtype is None else jnp.asarray(value, dtype)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"project_box: {name} must be a real array, got {value!r}") from exc
    if not (jnp.issubdtype(arr.dtype, jnp.floating) or jnp.issubdtype(arr.dtype, jnp.integer)):
        raise TypeError(f"project_box: {name} must be real, got dtype {arr.dtype}")
    return arr


def concrete(value):
    """The float64 NumPy value of a concrete input, or None when it is traced (also used by the
    eager checks of ``impact`` and ``timescale``)."""
    if is_traced(value):
        return None
    return np.asarray(value, dtype=np.float64)


def _finite(name, value):
    arr = concrete(value)
    if arr is not None and not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[:5].tolist()
        raise ValueError(f"project_box: {name} must be finite, got {arr[~np.isfinite(arr)][:5].tolist()} at {bad}")


def check_inputs(x_des, lower, upper, metric, G, h):
    """Validate and cast every input to one float dtype (that of ``x_des``, at least float32)."""
    x0 = _array("x_des", x_des)
    dtype = jnp.promote_types(x0.dtype, jnp.float32)
    if x0.ndim < 1:
        raise ValueError(f"project_box: x_des must have shape (..., n), got shape {x0.shape}")
    n = x0.shape[-1]
    if n < 1:
        raise ValueError(f"project_box: x_des must have at least one coordinate, got shape {x0.shape}")
    out = {"x_des": x0.astype(dtype)}
    for name, value in (("lower", lower), ("upper", upper)):
        arr = _array(name, value)
        if arr.ndim >= 1 and arr.shape[-1] != n:
            raise ValueError(f"project_box: {name} must be a scalar or end in n={n}, got shape {arr.shape}")
        _finite(name, arr)
        out[name] = arr.astype(dtype) if arr.ndim else jnp.broadcast_to(arr.astype(dtype), (n,))
    try:
        jnp.broadcast_shapes(x0.shape, out["lower"].shape, out["upper"].shape)
    except ValueError as exc:
        raise ValueError(
            f"project_box: shapes do not broadcast: x_des {x0.shape}, lower {out['lower'].shape}, "
            f"upper {out['upper'].shape}"
        ) from exc
    lo, hi = concrete(out["lower"]), concrete(out["upper"])
    if lo is not None and hi is not None:
        lo_b, hi_b = np.broadcast_arrays(lo, hi)
        bad = lo_b > hi_b
        if np.any(bad):
            idx = np.argwhere(bad)[:5].tolist()
            raise ValueError(
                f"project_box: need lower <= upper, got lower={lo_b[bad][:5].tolist()} > "
                f"upper={hi_b[bad][:5].tolist()} at {idx}"
            )

    W = _array("metric", metric)
    if W is not None:
        W = W.astype(dtype)
        if W.ndim == 1:
            if W.shape != (n,):
                raise ValueError(f"project_box: a diagonal metric must have shape ({n},), got {W.shape}")
            _finite("metric", W)
            w = concrete(W)
            if w is not None and np.any(w <= 0):
                raise ValueError(f"project_box: a diagonal metric must be > 0, got metric={w.tolist()}")
        elif W.ndim >= 2:
            if W.shape[-2:] != (n, n):
                raise ValueError(f"project_box: a dense metric must have shape (..., {n}, {n}), got {W.shape}")
            _finite("metric", W)
            w = concrete(W)
            if w is not None:
                scale = np.max(np.abs(w), axis=(-2, -1), keepdims=True)
                asym = np.max(np.abs(w - np.swapaxes(w, -1, -2)) / np.where(scale > 0, scale, 1.0))
                if asym > 1e-6:
                    raise ValueError(f"project_box: metric must be symmetric, got max |W - W^T| / max |W| = {asym:.3g}")
                eig = np.linalg.eigvalsh(0.5 * (w + np.swapaxes(w, -1, -2)))
                lam_min = eig[..., 0]
                bad = lam_min <= n * np.finfo(np.dtype(dtype)).eps * np.max(np.abs(eig), axis=-1)
                if np.any(bad):
                    raise ValueError(
                        "project_box: metric must be symmetric positive definite, got smallest eigenvalue "
                        f"{lam_min[bad].ravel()[:5].tolist()} (largest {np.max(eig[..., -1]):.3g})"
                    )
            # (symmetrised by the solver, in the layout it uses: one pass over W, not two)
        else:
            raise ValueError(f"project_box: metric must be None, (n,) or (..., n, n), got shape {W.shape}")

    if (G is None) != (h is None):
        got = f"G={'None' if G is None else 'an array'} and h={'None' if h is None else 'an array'}"
        raise ValueError(f"project_box: G and h go together, got {got}")
    if G is not None:
        G = _array("G", G).astype(dtype)
        h = _array("h", h).astype(dtype)
        if G.ndim < 2 or G.shape[-1] != n:
            raise ValueError(f"project_box: G must have shape (..., m, {n}), got {G.shape}")
        if h.ndim < 1 or h.shape[-1] != G.shape[-2]:
            raise ValueError(f"project_box: h must have shape (..., m) with m={G.shape[-2]} rows of G, got {h.shape}")
        _finite("G", G)
        _finite("h", h)
    return out["x_des"], out["lower"], out["upper"], W, G, h, dtype
