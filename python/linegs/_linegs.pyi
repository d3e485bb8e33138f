"""Type stubs of the native module (see ``linegs`` for the documented functions)."""

from typing import List, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import NDArray

__version__: str

class InputError(ValueError):
    """Bad input: an unreadable or malformed file, an invalid array or option."""

class LinegsError(RuntimeError):
    """A failure that is not the input's fault: the GPU, the file system."""

class Model:
    """A Gaussian model owned by the native module."""

    def __init__(
        self,
        centers: NDArray[np.float32],
        normals: Optional[NDArray[np.float32]] = None,
        max_scale: Optional[NDArray[np.float32]] = None,
        opacity: Optional[NDArray[np.float32]] = None,
        min_scale: Optional[NDArray[np.float32]] = None,
    ) -> None:
        """``centers`` and ``normals`` ``(N, 3)``, the others ``(N,)``: copied once."""
    def views(
        self,
    ) -> Tuple[
        NDArray[np.float32],
        Optional[NDArray[np.float32]],
        Optional[NDArray[np.float32]],
        Optional[NDArray[np.float32]],
        Optional[NDArray[np.float32]],
    ]:
        """``(centers (N, 3), normals (N, 3), max_scale (N,), opacity (N,), min_scale (N,))``."""
    def __len__(self) -> int: ...

def main(argv: Sequence[str]) -> int:
    """Runs the command line on ``argv`` (the program's name first); the exit code."""
def param_names() -> List[str]: ...
def formats() -> List[Tuple[str, str, str, List[str]]]: ...
def read_gaussians(path: str, min_opacity: Optional[float] = None, strict: bool = False) -> Tuple[Model, List[str]]: ...
def read_lines(path: str) -> Tuple[NDArray[np.float64], Optional[List[int]], List[str]]:
    """``((M, 2, 3) segments, groups, warnings)``."""
def write_lines(path: str, segments_f64: NDArray[np.float64]) -> None: ...
def refine(
    model: Model,
    segments_f64: NDArray[np.float64],
    groups: Optional[List[int]],
    args: List[Tuple[str, str]],
    backend_name: str,
    gt_f64: Optional[NDArray[np.float64]] = None,
    sweep: Optional[List[float]] = None,
    frame_check: bool = True,
    colmap: Optional[str] = None,
) -> Tuple[NDArray[np.float64], str]:
    """``segments_f64`` and ``gt_f64`` ``(M, 2, 3)``; returns ``(K, 2, 3)`` and the report JSON."""
def evaluate(
    model: Model,
    segments_f64: NDArray[np.float64],
    args: List[Tuple[str, str]],
    backend_name: str,
    compare_f64: Optional[NDArray[np.float64]] = None,
    gt_f64: Optional[NDArray[np.float64]] = None,
    sweep: Optional[List[float]] = None,
) -> str: ...
def release_device() -> None: ...
def devices_opened() -> int: ...
