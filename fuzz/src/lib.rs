//! The readers of linegs-gpu, compiled from the package's own sources (`src/geom/` and
//! `src/io/`) without the GPU stack: an instrumented build of wgpu and naga takes longer
//! than a fuzz run on a small machine, and the readers need none of it. The modules are
//! the same files the package builds, so what is fuzzed is what ships.

#[allow(unused)]
#[path = "../../src/geom/mod.rs"]
pub mod geom;

#[allow(unused)]
#[path = "../../src/io/mod.rs"]
pub mod io;

use std::path::Path;
use std::sync::OnceLock;

/// What every accepted line file must hold: finite, non-degenerate segments.
pub fn check_lines(name: &str, data: &[u8]) {
    if let Ok(f) = io::parse_lines(Path::new(name), data.to_vec()) {
        assert!(!f.lines.segments.is_empty());
        for s in &f.lines.segments {
            assert!(s.p1.is_finite() && s.p2.is_finite());
            assert!(s.length() > geom::MIN_LENGTH);
        }
        if let Some(g) = &f.lines.groups {
            assert_eq!(g.len(), f.lines.segments.len());
        }
    }
}

/// What every accepted Gaussian model must hold: finite centers, no more than declared.
pub fn check_gaussians(data: &[u8]) {
    for opts in [
        io::PlyOptions::default(),
        io::PlyOptions {
            min_opacity: Some(0.5),
            strict: true,
        },
    ] {
        let path = Path::new("fuzz.ply");
        let centers = io::parse_gaussians(path, data, &opts);
        if let Ok(c) = &centers {
            assert!(!c.centers.is_empty());
            assert!(c.centers.len() <= c.vertex_count);
            assert!(c.centers.iter().all(|p| p.iter().all(|v| v.is_finite())));
        }
        // The 3DGS reader with its attributes (one walk where the layout allows): the same
        // centers, and one attribute record per center.
        match io::parse_gaussians_and_attributes(path, data, &opts) {
            Ok((c, a)) => {
                assert_eq!(Some(&c), centers.as_ref().ok());
                if let Some(a) = a {
                    assert_eq!(a.normals.len(), c.centers.len());
                    assert_eq!(a.max_scale.len(), c.centers.len());
                    assert_eq!(a.min_scale.len(), c.centers.len());
                    assert!(a.opacity.is_none_or(|o| o.len() == c.centers.len()));
                }
            }
            Err(_) => assert!(centers.is_err()),
        }
    }
}

/// The file names the first byte of a `models` or `lines` input picks from: one per
/// extension of the format registry (`io::file_names`), so a new format is fuzzed under
/// its own name.
fn names(gaussians: bool) -> &'static [String] {
    static MODELS: OnceLock<Vec<String>> = OnceLock::new();
    static LINES: OnceLock<Vec<String>> = OnceLock::new();
    match gaussians {
        true => MODELS.get_or_init(|| io::file_names("m", true)),
        false => LINES.get_or_init(|| io::file_names("l", false)),
    }
}

/// Every Gaussian model format of the registry; the first byte picks the file name, whose
/// extension tells a format without a signature (`.splat`).
pub fn check_models(data: &[u8]) {
    let Some((&k, rest)) = data.split_first() else {
        return;
    };
    let names = names(true);
    let path = Path::new(&names[k as usize % names.len()]);
    if let Ok(c) = io::parse_gaussian_model(path, rest, &io::PlyOptions::default()) {
        assert!(!c.centers.is_empty());
        assert!(c.centers.iter().all(|p| p.iter().all(|v| v.is_finite())));
    }
}

/// Every line format of the registry, picked by content; the first byte picks the file
/// name, whose extension decides what content alone cannot (a broken binary STL, an OBJ).
pub fn check_picked_lines(data: &[u8]) {
    if let Some((&k, rest)) = data.split_first() {
        let names = names(false);
        check_lines(&names[k as usize % names.len()], rest);
    }
}
