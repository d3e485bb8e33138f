import os
from typing import Any, Dict, Optional, Sequence, Tuple, Union

import numpy as np

from ._linegs import InputError as InputError, LinegsError as LinegsError

__version__: str
PARAMS: Tuple[str, ...]
PathLike = Union[str, os.PathLike[str]]

class Gaussians:
    centers: np.ndarray
    normals: Optional[np.ndarray]
    max_scale: Optional[np.ndarray]
    opacity: Optional[np.ndarray]
    min_scale: Optional[np.ndarray]
    def __init__(self, centers: Any, normals: Any = None, max_scale: Any = None, opacity: Any = None, min_scale: Any = None) -> None: ...
    def __len__(self) -> int: ...
    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray: ...

def read_gaussians(path: PathLike, min_opacity: Optional[float] = None, *, strict: bool = False) -> Gaussians: ...
def read_lines(path: PathLike, *, groups: bool = False) -> Any: ...
def write_lines(path: PathLike, segments: Any) -> None: ...
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
    **params: Any,
) -> Tuple[np.ndarray, Dict[str, Any]]: ...
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
) -> Dict[str, Any]: ...
