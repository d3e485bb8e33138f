//! Files in, files out (docs/formats.md): Gaussian models and line segments in every format the
//! line-reconstruction tools write, detected by content; writers that never leave a partial
//! file; and `info` for a quick look at either.

mod attributes;
mod chunked;
mod colmap;
mod edges_json;
mod error;
mod format;
mod gaussians;
mod info;
mod input;
mod journal;
mod limap;
mod line3dpp;
mod lines;
mod litter;
mod normals;
mod npy;
pub mod obj;
mod output;
mod plain;
mod ply;
mod ply_3dgs;
mod ply_compressed;
mod ply_lines;
mod registry;
mod sink;
mod splat;
mod spz;
mod stl;
mod text;
mod transform;
mod write;

pub use colmap::{
    read_colmap, write_colmap_binary, write_colmap_text, Camera, ColmapModel, Image, Point3D,
    CAMERA_MODELS,
};
pub use edges_json::{edges_json_text, POLYLINE_PIECES};
pub use error::{Error, KnownFormats, Position};
pub use format::{Curves, GaussianFormat, LineFormat, LineOptions, LineWriter};
pub use gaussians::{
    detect_gaussians, is_gaussian_model, parse_gaussian_model, parse_gaussians_and_attributes,
    read_gaussians, read_gaussians_and_attributes, read_gaussians_with_opacity,
};
pub use info::{info, info_with, FileInfo, FileKind};
pub use input::STREAM_LIMIT;
pub use journal::recover as finish_output_sets;
#[cfg(test)]
pub(crate) use journal::Stop;
pub use limap::{read_supports, track_text, Support};
pub use litter::{
    clean_stale_runtime_dirs, clean_stale_runtime_dirs_in, clean_stale_temps, temp_prefix,
    try_lock, RUNTIME_PREFIX, STALE_AGE,
};

pub use attributes::GaussianAttributes;
pub(crate) use input::{read_input, read_small};
pub use line3dpp::read_line3dpp_supports;
pub use lines::{
    check_line_output, parse_lines, parse_lines_with, read_lines, read_lines_with, write_lines,
    LineFile, LINE_OUTPUTS,
};
pub use normals::{parse_gaussian_attributes, read_gaussian_attributes, read_gaussian_normals};
pub use output::{same_file, OutputSet, PathIndex};
pub use ply::{parse_gaussians, GaussianCloud, PlyOptions};
pub use registry::{
    file_names, format_table, gaussian_family_words, gaussian_format, gaussian_format_words,
    known_formats, line_format, line_format_words, line_output_words, GAUSSIAN_FORMATS,
    LINE_FORMATS, LINE_WRITERS,
};
pub use spz::encode_spz;
pub use transform::{read_transform, GaussianTransform};
pub use write::{
    check_output_extension, gaussian_3dgs_properties, write_bytes_atomic, write_gaussians_3dgs,
    write_gaussians_ply, write_lines_line3dpp, write_lines_ply_layers, DEFAULT_LINE_COLOR,
    DEFAULT_OPACITY_LOGIT,
};
