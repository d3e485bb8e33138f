use super::{load_framed, InputArgs};
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
    /// The picture to write (`.png`).
    #[arg(short, long, value_name = "PNG")]
    pub output: PathBuf,
    /// Also write a self-contained HTML viewer (`.html`: orbit, zoom, toggle layers).
    #[arg(long, value_name = "HTML")]
    pub viewer: Option<PathBuf>,
    /// Width of the picture in pixels (64 to 16384).
    #[arg(long, default_value_t = 1600, value_parser = clap::value_parser!(u32).range(64..=16384))]
    pub width: u32,
    /// Height of the picture in pixels (64 to 16384).
    #[arg(long, default_value_t = 900, value_parser = clap::value_parser!(u32).range(64..=16384))]
    pub height: u32,
}

pub const BEFORE: [u8; 3] = render::INPUT_COLOR;
pub const AFTER: [u8; 3] = render::REFINED_COLOR;

pub fn run(a: RenderArgs) -> Result<()> {
    let mut outs = super::outputs(&a.input);
    if let Some(p) = &a.lines_after {
        outs.input(p);
    }
    outs.output("-o", &a.output, &["png"]);
    if let Some(v) = &a.viewer {
        outs.output("--viewer", v, &["html", "htm"]);
    }
    outs.check()?;
    let scene = load_framed(&a.input, &linegs_gpu::refine::Params::default(), true)?;
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
    crate::oom::doing(
        format!("drawing a {} x {} picture", a.width, a.height),
        "give a smaller --width and --height",
    );
    let img = render::render_comparison(&scene.gaussians, &panels, a.width, a.height);
    outs.write(&a.output, |p| img.write_png(p))?;
    if let Some(v) = &a.viewer {
        let layers = render::viewer_layers(before, after.as_ref().map(|a| &a.segments[..]), None);
        let html = render::viewer_html(&scene.gaussians, &layers, "linegs-gpu", 200_000);
        outs.write(v, |p| io::write_bytes_atomic(p, html.as_bytes()))?;
    }
    outs.commit()?;
    println!("wrote {}", a.output.display());
    if let Some(v) = &a.viewer {
        println!("wrote {}", v.display());
    }
    Ok(())
}
