"""linegs: refine noisy 3D line segments with the Gaussian centers of a trained 3D Gaussian
Splatting model (the LineGS method), on the CPU or the GPU.

The Python face of ``linegs-gpu``: the same library entry point as the command line, so
``refine`` returns exactly the segments that ``linegs-gpu refine`` writes, and the report
dict has the shape of ``linegs-gpu refine --report``.

>>> import linegs
>>> g = linegs.read_gaussians("point_cloud.ply")          # Gaussians: centers + attributes
>>> lines = linegs.read_lines("Line3D++.obj")             # (M, 2, 3) float64
>>> refined, report = linegs.refine(g, lines, radius=0.05)
>>> report["after"]["score"]

``refine`` and ``evaluate`` take the Gaussians as a :class:`Gaussians` (what
``read_gaussians`` returns: the file's centers and attributes, the command line's answer
bit for bit), as a path (read the same way), or as a plain ``(N, 3)`` array of centers:
centers only, so the edge fit and the scale cut (``max_scale``) see no attributes.

No array is copied on the way: a :class:`Gaussians` owns its arrays in the native module
and shows them as read-only numpy views, which ``refine`` and ``evaluate`` compute on in
place; segments are read from the caller's arrays where they lie, and results come back
as arrays that own the native result.
"""

from __future__ import annotations

import json
import os
from typing import Any, Dict, Optional, Sequence, Tuple, Union

import numpy as np

from . import _linegs
from ._linegs import InputError, LinegsError

__all__ = [
    "FORMATS",
    "Gaussians",
    "InputError",
    "LinegsError",
    "PARAMS",
    "evaluate",
    "read_gaussians",
    "read_lines",
    "refine",
    "release_device",
    "write_lines",
]
__version__: str = _linegs.__version__

PathLike = Union[str, "os.PathLike[str]"]

#: Every refinement parameter ``refine`` accepts as a keyword (the command line's
#: ``--kebab-case`` options with underscores), e.g. ``translate_keep``, ``fix_join_gap``.
PARAMS: Tuple[str, ...] = tuple(_linegs.param_names())

#: Every file format, from the library's one list of formats: ``(kind, id, name,
#: extensions)``, kind ``"gaussians"`` (what :func:`read_gaussians` reads), ``"lines"``
#: (what :func:`read_lines` reads) or ``"output"`` (what :func:`write_lines` writes, chosen
#: by the extension), e.g. ``("gaussians", "splat", "antimatter15 .splat", ("splat",))``.
FORMATS: Tuple[Tuple[str, str, str, Tuple[str, ...]], ...] = tuple(
    (kind, id_, name, tuple(exts)) for kind, id_, name, exts in _linegs.formats()
)


def _warn(warnings: Sequence[str]) -> None:
    import warnings as w

    for msg in warnings:
        w.warn(msg, stacklevel=3)


class Gaussians:
    """A 3DGS model as the refinement sees it: ``centers`` ``(N, 3)`` float32 and, where
    the file has them (a PLY with rotations, scales and opacities, e.g. the standard
    62-property layout), ``normals`` ``(N, 3)`` (each Gaussian's shortest axis, zero where
    it is not flat), ``max_scale`` ``(N,)`` (its largest standard deviation, scene units),
    ``opacity`` ``(N,)`` (in ``[0, 1]``) and ``min_scale`` ``(N,)`` (its smallest standard
    deviation: a flat Gaussian's thickness); ``None``
    where it does not.

    The arrays are read-only views of the model's own memory in the native module (the
    reader's, for :func:`read_gaussians`; no copy). Built from arrays, the model copies
    them once (any float dtype and layout); build a new one to change them.

    ``normals`` and ``max_scale`` come together; every array has one row per center.
    ``np.asarray(g)`` is the centers.
    """

    __slots__ = ("centers", "normals", "max_scale", "opacity", "min_scale", "_model")

    def __init__(
        self,
        centers: Any,
        normals: Any = None,
        max_scale: Any = None,
        opacity: Any = None,
        min_scale: Any = None,
    ) -> None:
        c = np.asarray(centers, dtype=np.float32)
        if c.ndim != 2 or c.shape[1] != 3:
            raise InputError(f"gaussians: expected an (N, 3) array of centers, got shape {c.shape}")
        n = len(c)

        def attr(a: Any, shape: Tuple[int, ...], what: str) -> Any:
            if a is None:
                return None
            a = np.asarray(a, dtype=np.float32)
            if a.shape != shape:
                raise InputError(f"gaussians: {what} has shape {a.shape}, expected {shape}")
            return a

        normals = attr(normals, (n, 3), "normals")
        max_scale = attr(max_scale, (n,), "max_scale")
        opacity = attr(opacity, (n,), "opacity")
        min_scale = attr(min_scale, (n,), "min_scale")
        if (normals is None) != (max_scale is None):
            raise InputError("gaussians: normals and max_scale come together (or neither)")
        self._adopt(_linegs.Model(c, normals, max_scale, opacity, min_scale))

    def _adopt(self, model: Any) -> None:
        self._model = model
        views = model.views()
        for v in views:
            if v is not None:
                v.flags.writeable = False
        self.centers, self.normals, self.max_scale, self.opacity, self.min_scale = views

    @classmethod
    def _of(cls, model: Any) -> "Gaussians":
        g = cls.__new__(cls)
        g._adopt(model)
        return g

    def __len__(self) -> int:
        return len(self.centers)

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        return self.centers if dtype is None else self.centers.astype(dtype)

    def __repr__(self) -> str:
        has = [k for k in ("normals", "max_scale", "opacity", "min_scale") if getattr(self, k) is not None]
        return f"Gaussians({len(self)} centers; attributes: {', '.join(has) or 'none'})"


def read_gaussians(path: PathLike, min_opacity: Optional[float] = None, *, strict: bool = False) -> Gaussians:
    """A 3DGS model in any ``"gaussians"`` format of :data:`FORMATS` as :class:`Gaussians`:
    its centers and the attributes the file has, exactly as ``linegs-gpu refine`` reads
    them (the arrays are the reader's own memory, not a copy).

    ``min_opacity`` keeps only Gaussians with ``sigmoid(opacity) >= min_opacity``. Centers
    that are NaN or infinite are skipped with a warning (an error with ``strict=True``).
    Raises :class:`InputError` naming the file and the place for a bad file.
    """
    model, warnings = _linegs.read_gaussians(os.fspath(path), min_opacity, strict)
    _warn(warnings)
    return Gaussians._of(model)


def read_lines(path: PathLike, *, groups: bool = False) -> Any:
    """Line segments of any ``"lines"`` format of :data:`FORMATS`: ``(M, 2, 3)`` float64,
    endpoints ``[:, 0]`` and ``[:, 1]``. Degenerate segments are dropped with a warning.

    With ``groups=True`` returns ``(segments, groups)``, where ``groups`` is the input
    line of each segment (``(M,)`` uint32; Line3D++ ``.txt``) or ``None``; pass it on to
    :func:`refine` so the collinear merge sees the lines, as the command line does.
    """
    segs, g, warnings = _linegs.read_lines(os.fspath(path))
    _warn(warnings)
    if groups:
        return segs, (None if g is None else np.asarray(g, dtype=np.uint32))
    return segs


def write_lines(path: PathLike, segments: Any) -> None:
    """Writes ``(K, 2, 3)`` segments, atomically; the format follows the extension (the
    ``"output"`` formats of :data:`FORMATS`)."""
    _linegs.write_lines(os.fspath(path), _segments(segments, "segments"))


def _gaussians(g: Any) -> Any:
    """The native model of the Gaussians: a :class:`Gaussians`, a path, or an ``(N, 3)``
    array of centers (no attributes; copied once into a model)."""
    if isinstance(g, (str, os.PathLike)):
        g = read_gaussians(g)
    if not isinstance(g, Gaussians):
        g = Gaussians(g)
    return g._model


def _segments(a: Any, what: str) -> np.ndarray:
    """``(M, 2, 3)`` float64 (``(M, 6)`` is taken too), a view where ``a`` is float64."""
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 2 and a.shape[1] == 6:
        a = a.reshape(-1, 2, 3)
    if a.ndim != 3 or a.shape[1:] != (2, 3):
        raise InputError(f"{what}: expected an (M, 2, 3) array of segments, got shape {a.shape}")
    return a


def _args(params: Dict[str, Any]) -> list:
    unknown = sorted(set(params) - set(PARAMS))
    if unknown:
        raise TypeError(
            f"unexpected keyword argument{'s' if len(unknown) > 1 else ''} "
            f"{', '.join(repr(u) for u in unknown)}; the parameters are: {', '.join(PARAMS)}"
        )
    out = []
    for k, v in params.items():
        if v is None:
            continue
        if isinstance(v, bool):
            v = "true" if v else "false"
        elif isinstance(v, float):
            v = repr(v)
        out.append((k, str(v)))
    return out


def refine(
    gaussians: Any,
    segments: Any,
    *,
    radius: Union[float, str] = 0.03,
    eval_radius: float = 0.1,
    profile: str = "default",
    backend: str = "auto",
    groups: Any = None,
    gt: Any = None,
    radii: Optional[Sequence[float]] = None,
    frame_check: bool = True,
    colmap: Optional[Union[str, os.PathLike]] = None,
    **params: Any,
) -> Tuple[np.ndarray, Dict[str, Any]]:
    """Refines ``segments`` ``(M, 2, 3)`` against the Gaussians (LineGS:
    translate, outliers, collinear merge, cluster, merge and join, crop) and returns the
    refined ``(K, 2, 3)`` float64 segments and the report dict (``before``/``after``
    metrics, ``stages``, ``params``, ...), the same as ``linegs-gpu refine``.

    ``gaussians``: a :class:`Gaussians` (from :func:`read_gaussians`), a path to the model,
    or an ``(N, 3)`` array of centers (centers only: the edge fit and the scale cut see no
    attributes, so the result differs from the command line's on a file that has them).
    ``radius``: the cylinder radius in scene units, or ``"auto"``. ``profile``:
    ``"default"`` (the paper's intent) or ``"reference"`` (the authors' code).
    ``backend``: ``"auto"``, ``"gpu"`` or ``"cpu"``. ``groups``: the input line of each
    segment (see :func:`read_lines`). ``gt``: ground-truth edges for the ABC-NEF metrics
    (``report["ground_truth"]``). ``radii``: a radius sweep (``report["sweep"]``).
    Every other parameter of :data:`PARAMS` is a keyword, e.g. ``translate_keep=0.4``.

    The frame check of ``linegs-gpu refine`` runs first: when (almost) no segment has a
    Gaussian center within ``r`` (lines and model in different frames or units), it raises
    :class:`InputError` with the command line's message; ``frame_check=False`` refines
    anyway (``--no-frame-check``). A doubtful frame is a warning in ``report["warnings"]``.
    ``colmap``: the COLMAP sparse model (folder, text or binary) the Gaussians were trained
    from, as ``--colmap``: where the lines and the Gaussians are not in one frame, the
    normalization gsplat or nerfstudio applied is recomputed from it and undone on a copy of
    the centers (the found matrix and its residual in ``report["warnings"]``).

    The computation runs without the GIL. Raises :class:`InputError` for bad arrays or
    options (with the command line's messages), :class:`LinegsError` otherwise.
    """
    args = _args(dict(radius=radius, eval_radius=eval_radius, profile=profile, **params))
    g = None if groups is None else [int(x) for x in np.asarray(groups).ravel()]
    segs, report = _linegs.refine(
        _gaussians(gaussians),
        _segments(segments, "segments"),
        g,
        args,
        backend,
        gt_f64=None if gt is None else _segments(gt, "gt"),
        sweep=None if radii is None else [float(r) for r in radii],
        frame_check=bool(frame_check),
        colmap=None if colmap is None else os.fspath(colmap),
    )
    return segs, json.loads(report)


def evaluate(
    gaussians: Any,
    segments: Any,
    *,
    eval_radius: float = 0.1,
    gt: Any = None,
    compare: Any = None,
    radii: Optional[Sequence[float]] = None,
    profile: str = "default",
    backend: str = "auto",
    **params: Any,
) -> Dict[str, Any]:
    """The paper's metrics of ``segments`` (E_rms, R_covered, R_L, score) at
    ``eval_radius``, as ``linegs-gpu eval --json``: ``report["before"]`` for
    ``segments``, ``report["after"]`` for ``compare`` (measured on the same working set),
    ``report["ground_truth"]`` against ``gt``, ``report["sweep"]`` at ``radii``.
    ``gaussians`` as for :func:`refine`. Keywords as for :func:`refine` (``unit_scale``,
    ``score_lambda``, ``r_l``, ...). The frame check warns in ``report["warnings"]``, as
    ``linegs-gpu eval`` does."""
    args = _args(dict(eval_radius=eval_radius, profile=profile, **params))
    report = _linegs.evaluate(
        _gaussians(gaussians),
        _segments(segments, "segments"),
        args,
        backend,
        compare_f64=None if compare is None else _segments(compare, "compare"),
        gt_f64=None if gt is None else _segments(gt, "gt"),
        sweep=None if radii is None else [float(r) for r in radii],
    )
    return json.loads(report)


def release_device() -> None:
    """Lets go of the GPU device that :func:`refine` and :func:`evaluate` keep open between
    calls. The first call with ``backend="gpu"`` (or ``"auto"`` on a machine with a GPU)
    opens the adapter and compiles the kernels; later calls with the same backend and GPU
    settings reuse them, so that a loop over many small scenes pays that once. Each call's
    Gaussians are freed when it returns either way; after this, the next GPU call opens
    the device again."""
    _linegs.release_device()
