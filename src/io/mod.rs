//! Files in, files out (SPEC 6): Gaussian models and line segments in every format the
//! line-reconstruction tools write, detected by content; writers that never leave a partial
//! file; and `info` for a quick look at either.

mod chunked;
mod error;
mod info;
mod lines;
mod normals;
mod npy;
mod ply;
mod write;

pub use error::{Error, Position, KNOWN_FORMATS};
pub use info::{info, FileInfo, FileKind};
pub use lines::{read_lines, LineFile, LineFormat};
pub use normals::read_gaussian_normals;
pub use ply::{read_gaussians, GaussianCloud, PlyOptions};
pub use write::{
    check_line_output, gaussian_3dgs_properties, write_bytes_atomic, write_gaussians_3dgs,
    write_lines, write_lines_ply_layers, DEFAULT_LINE_COLOR, DEFAULT_OPACITY_LOGIT, LINE_OUTPUTS,
};
