use anyhow::Result;
use clap::Args;
use linegs_gpu::io;
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct InfoArgs {
    /// A Gaussian model (PLY) or a line file in any supported format.
    pub file: PathBuf,
}

pub fn run(a: InfoArgs) -> Result<()> {
    let info = io::info(&a.file)?;
    print!("{info}");
    Ok(())
}
