//! Files in, files out (SPEC 6): Gaussian models and line segments in every format the
//! line-reconstruction tools write, detected by content; writers that never leave a partial
//! file; and `info` for a quick look at either.

mod chunked;
mod edges_json;
mod error;
mod gaussians;
mod info;
mod limap;
mod lines;
mod npy;
mod ply;
mod ply_compressed;
mod splat;
mod spz;
mod transform;
mod write;

pub use edges_json::{Curves, POLYLINE_PIECES};
pub use error::{Error, Position, KNOWN_FORMATS};
pub use gaussians::{
    detect_gaussians, is_gaussian_model, read_gaussians, read_gaussians_with_opacity,
    write_gaussians_ply, GaussianFormat,
};
pub use info::{info, info_with, FileInfo, FileKind};
pub use lines::{read_lines, read_lines_with, LineFile, LineFormat, LineOptions};
pub use ply::{GaussianCloud, PlyOptions};
pub use spz::encode_spz;
pub use transform::{read_transform, GaussianTransform};
pub use write::{
    check_line_output, gaussian_3dgs_properties, write_bytes_atomic, write_gaussians_3dgs,
    write_lines, write_lines_ply_layers, DEFAULT_LINE_COLOR, DEFAULT_OPACITY_LOGIT, LINE_OUTPUTS,
};
