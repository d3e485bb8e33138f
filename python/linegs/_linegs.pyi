"""Type stubs of the native module (see ``linegs`` for the documented functions)."""

from typing import List, Optional, Tuple

__version__: str

class InputError(ValueError):
    """Bad input: an unreadable or malformed file, an invalid array or option."""

class LinegsError(RuntimeError):
    """A failure that is not the input's fault: the GPU, the file system."""

def param_names() -> List[str]: ...
def read_gaussians(
    path: str, min_opacity: Optional[float] = None, strict: bool = False
) -> Tuple[bytes, Optional[bytes], Optional[bytes], Optional[bytes], Optional[bytes], List[str]]: ...
def read_lines(path: str) -> Tuple[bytes, Optional[List[int]], List[str]]: ...
def write_lines(path: str, segments_f64: bytes) -> None: ...
def refine(
    gaussians_f32: bytes,
    segments_f64: bytes,
    groups: Optional[List[int]],
    args: List[Tuple[str, str]],
    backend_name: str,
    gt_f64: Optional[bytes] = None,
    sweep: Optional[List[float]] = None,
    normals_f32: Optional[bytes] = None,
    max_scale_f32: Optional[bytes] = None,
    opacity_f32: Optional[bytes] = None,
    min_scale_f32: Optional[bytes] = None,
) -> Tuple[bytes, str]: ...
def evaluate(
    gaussians_f32: bytes,
    segments_f64: bytes,
    args: List[Tuple[str, str]],
    backend_name: str,
    compare_f64: Optional[bytes] = None,
    gt_f64: Optional[bytes] = None,
    sweep: Optional[List[float]] = None,
    normals_f32: Optional[bytes] = None,
    max_scale_f32: Optional[bytes] = None,
    opacity_f32: Optional[bytes] = None,
    min_scale_f32: Optional[bytes] = None,
) -> str: ...
