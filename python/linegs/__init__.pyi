import os
from typing import Any, Dict, Literal, Optional, Sequence, Tuple, Union, overload

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._linegs import InputError as InputError, LinegsError as LinegsError

__version__: str
PARAMS: Tuple[str, ...]
FORMATS: Tuple[Tuple[str, str, str, Tuple[str, ...]], ...]
PathLike = Union[str, os.PathLike[str]]

class Gaussians:
    """A model's arrays, read-only views of the native model's memory.

    - ``centers``: ``(N, 3)`` float32
    - ``normals``: ``(N, 3)`` float32 or ``None``
    - ``max_scale``, ``opacity``, ``min_scale``: ``(N,)`` float32 or ``None``
    """

    centers: NDArray[np.float32]
    normals: Optional[NDArray[np.float32]]
    max_scale: Optional[NDArray[np.float32]]
    opacity: Optional[NDArray[np.float32]]
    min_scale: Optional[NDArray[np.float32]]
    def __init__(
        self,
        centers: ArrayLike,
        normals: Optional[ArrayLike] = None,
        max_scale: Optional[ArrayLike] = None,
        opacity: Optional[ArrayLike] = None,
        min_scale: Optional[ArrayLike] = None,
    ) -> None:
        """``centers`` ``(N, 3)``, ``normals`` ``(N, 3)``, the others ``(N,)``; copied once."""
    def __len__(self) -> int: ...
    def __array__(self, dtype: Any = None, copy: Any = None) -> NDArray[np.float32]: ...

def read_gaussians(path: PathLike, min_opacity: Optional[float] = None, *, strict: bool = False) -> Gaussians: ...
@overload
def read_lines(path: PathLike, *, groups: Literal[False] = False) -> NDArray[np.float64]:
    """``(M, 2, 3)`` float64 segments."""
@overload
def read_lines(
    path: PathLike, *, groups: Literal[True]
) -> Tuple[NDArray[np.float64], Optional[NDArray[np.uint32]]]:
    """``(M, 2, 3)`` float64 segments and ``(M,)`` uint32 groups (or ``None``)."""
def write_lines(path: PathLike, segments: ArrayLike) -> None:
    """``segments``: ``(K, 2, 3)`` (or ``(K, 6)``), any float dtype."""
def refine(
    gaussians: Union[Gaussians, PathLike, ArrayLike],
    segments: ArrayLike,
    *,
    radius: Union[float, str] = 0.03,
    eval_radius: float = 0.1,
    profile: str = "default",
    backend: str = "auto",
    groups: Optional[ArrayLike] = None,
    gt: Optional[ArrayLike] = None,
    radii: Optional[Sequence[float]] = None,
    frame_check: bool = True,
    colmap: Optional[PathLike] = None,
    **params: Any,
) -> Tuple[NDArray[np.float64], Dict[str, Any]]:
    """``gaussians``: a model, a path or ``(N, 3)`` centers; ``segments`` and ``gt``:
    ``(M, 2, 3)``; ``groups``: ``(M,)``. Returns the ``(K, 2, 3)`` float64 segments and
    the report."""
def evaluate(
    gaussians: Union[Gaussians, PathLike, ArrayLike],
    segments: ArrayLike,
    *,
    eval_radius: float = 0.1,
    gt: Optional[ArrayLike] = None,
    compare: Optional[ArrayLike] = None,
    radii: Optional[Sequence[float]] = None,
    profile: str = "default",
    backend: str = "auto",
    **params: Any,
) -> Dict[str, Any]:
    """``segments``, ``compare`` and ``gt``: ``(M, 2, 3)``."""
def release_device() -> None: ...
