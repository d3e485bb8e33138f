use super::FrameArgs;
use anyhow::Result;
use clap::Args;
use linegs_gpu::geom::{p64, Aabb};
use linegs_gpu::io::{self, PlyOptions};
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct InfoArgs {
    // The formats' words come from the format registry (io::GAUSSIAN_FORMATS).
    #[arg(help = format!(
        "A Gaussian model ({}) or a line file (or LIMAP finaltracks/ folder) in any supported format",
        io::gaussian_family_words(false)
    ))]
    pub file: PathBuf,
    #[command(flatten)]
    pub frame: FrameArgs,
}

pub fn run(a: InfoArgs) -> Result<()> {
    // A set that a killed run committed in the file's folder is finished first, as every
    // command that reads does; a folder it cannot be finished in (read-only) is read as
    // it is.
    let folder = match a.file.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => std::path::Path::new("."),
    };
    let _ = io::finish_output_sets(folder);
    let mut info = io::info_with(&a.file, &a.frame.line_options())?;
    if a.frame.gaussians_transform.is_some() && info.kind == io::FileKind::Gaussians {
        // The box as the lines would see it.
        let mut cloud = io::read_gaussians(&a.file, &PlyOptions::default())?;
        a.frame.transform(&mut cloud)?;
        let mut bbox = Aabb::empty();
        for c in &cloud.centers {
            bbox.extend(p64(*c));
        }
        info.bbox = bbox;
    }
    print!("{info}");
    Ok(())
}
