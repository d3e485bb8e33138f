use super::FrameArgs;
use anyhow::Result;
use clap::Args;
use linegs_gpu::geom::{p64, Aabb};
use linegs_gpu::io::{self, PlyOptions};
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct InfoArgs {
    /// A Gaussian model (3DGS or SuperSplat compressed PLY, SPZ, .splat) or a line file
    /// (or LIMAP finaltracks/ folder) in any supported format.
    pub file: PathBuf,
    #[command(flatten)]
    pub frame: FrameArgs,
}

pub fn run(a: InfoArgs) -> Result<()> {
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
