use super::{load, InputArgs};
use anyhow::Result;
use clap::Args;
use linegs_gpu::io;
use linegs_gpu::render::{self, Layer, Panel};
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct RenderArgs {
    #[command(flatten)]
    pub input: InputArgs,
    /// A second segment set (e.g. the refined lines), drawn in its own panel.
    #[arg(long, value_name = "FILE")]
    pub lines_after: Option<PathBuf>,
    /// The PNG to write.
    #[arg(short, long, value_name = "PNG")]
    pub output: PathBuf,
    /// Also write a self-contained HTML viewer (orbit, zoom, toggle layers).
    #[arg(long, value_name = "HTML")]
    pub viewer: Option<PathBuf>,
    #[arg(long, default_value_t = 1600)]
    pub width: u32,
    #[arg(long, default_value_t = 900)]
    pub height: u32,
}

pub const BEFORE: [u8; 3] = [220, 60, 40];
pub const AFTER: [u8; 3] = [30, 100, 230];

pub fn run(a: RenderArgs) -> Result<()> {
    let scene = load(&a.input)?;
    let after = match &a.lines_after {
        Some(p) => Some(io::read_lines(p)?.lines),
        None => None,
    };
    let before = &scene.lines.segments;
    let mut panels = vec![Panel {
        title: "input",
        layers: vec![Layer {
            name: "input segments",
            segments: before,
            color: BEFORE,
        }],
        metrics: vec![format!("{} segments", before.len())],
    }];
    if let Some(af) = &after {
        panels.push(Panel {
            title: "refined",
            layers: vec![Layer {
                name: "refined segments",
                segments: &af.segments,
                color: AFTER,
            }],
            metrics: vec![format!("{} segments", af.len())],
        });
    }
    let img = render::render_comparison(&scene.gaussians, &panels, a.width, a.height);
    img.write_png(&a.output)?;
    println!("wrote {}", a.output.display());
    if let Some(v) = &a.viewer {
        let mut layers = vec![Layer {
            name: "input segments",
            segments: before,
            color: BEFORE,
        }];
        if let Some(af) = &after {
            layers.push(Layer {
                name: "refined segments",
                segments: &af.segments,
                color: AFTER,
            });
        }
        let html = render::viewer_html(&scene.gaussians, &layers, "linegs-gpu", 200_000);
        io::write_bytes_atomic(v, html.as_bytes())?;
        println!("wrote {}", v.display());
    }
    Ok(())
}
