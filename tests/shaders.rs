//! Every kernel parses and validates with naga, without a GPU: a shader typo fails here,
//! not in a user's run. And every struct the host and the kernels share has, in naga's
//! reflection of each kernel, the offsets and size of the Rust struct the host writes.

use linegs_gpu::engine::gpu::{common_wgsl, f64_kernel_source, kernel_source, layout};
use std::path::Path;

/// A kernel as the engine loads it: the generated prelude and `common.wgsl` first.
fn source(path: &Path) -> Result<String, String> {
    let src = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(if path.file_name().is_some_and(|n| n == "common.wgsl") {
        common_wgsl()
    } else if is_fit(path) {
        f64_kernel_source(&src)
    } else {
        kernel_source(&src)
    })
}

/// The fit and extent kernels run in f64: the kernels that need a capability
/// (`SHADER_F64`), and those with the f64 shared structs.
fn is_fit(path: &Path) -> bool {
    path.file_name()
        .is_some_and(|n| n == "fit.wgsl" || n == "extent.wgsl")
}

fn parse(src: &str, path: &Path) -> Result<naga::Module, String> {
    naga::front::wgsl::parse_str(src)
        .map_err(|e| e.emit_to_string_with_path(src, path.to_string_lossy().as_ref()))
}

fn validate(path: &Path) -> Result<naga::valid::ModuleInfo, String> {
    let src = source(path)?;
    let module = parse(&src, path)?;
    naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        // No subgroups, nothing beyond core WebGPU; f64 in the fit kernel only.
        if is_fit(path) {
            naga::valid::Capabilities::FLOAT64
        } else {
            naga::valid::Capabilities::empty()
        },
    )
    .validate(&module)
    .map_err(|e| e.emit_to_string_with_path(&src, path.to_string_lossy().as_ref()))
}

fn shader_dir() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("shaders")
}

fn kernels() -> Vec<std::path::PathBuf> {
    let mut v: Vec<_> = std::fs::read_dir(shader_dir())
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "wgsl"))
        .collect();
    v.sort();
    v
}

#[test]
fn every_shader_is_valid_wgsl() {
    let mut names = Vec::new();
    for path in kernels() {
        if let Err(e) = validate(&path) {
            panic!("{e}");
        }
        names.push(path.file_name().unwrap().to_string_lossy().into_owned());
    }
    assert_eq!(
        names,
        [
            "args.wgsl",
            "common.wgsl",
            "cut.wgsl",
            "eval.wgsl",
            "extent.wgsl",
            "fit.wgsl",
            "members.wgsl",
            "reduce.wgsl",
            "scan.wgsl",
            "walk.wgsl"
        ]
    );
}

/// The workgroup size the host dispatches each entry point with: the constants of
/// `layout.rs`, which the prelude declares for the kernels.
fn host_workgroup(file: &str) -> u32 {
    match file {
        "args.wgsl" => 1,
        "scan.wgsl" => layout::SCAN_WG,
        "fit.wgsl" | "extent.wgsl" => layout::FIT_WG,
        _ => layout::WG,
    }
}

/// The `@workgroup_size` of every entry point of `src`, as naga reads it.
fn workgroup_sizes(src: &str, path: &Path) -> Vec<(String, [u32; 3])> {
    let module = parse(src, path).unwrap_or_else(|e| panic!("{e}"));
    module
        .entry_points
        .iter()
        .map(|e| (e.name.clone(), e.workgroup_size))
        .collect()
}

#[test]
fn every_kernel_runs_the_workgroup_size_the_host_dispatches() {
    for path in kernels() {
        let file = path.file_name().unwrap().to_string_lossy().into_owned();
        let src = source(&path).unwrap();
        let want = host_workgroup(&file);
        for (entry, size) in workgroup_sizes(&src, &path) {
            assert_eq!(size, [want, 1, 1], "{file}: {entry}");
        }
        // The size comes from the prelude's constant, not a literal: changing the
        // constant changes the kernel.
        if want > 1 {
            let name = match file.as_str() {
                "scan.wgsl" => "SCAN_WG",
                "fit.wgsl" | "extent.wgsl" => "FIT_WG",
                _ => "WG",
            };
            let decl = format!("const {name}: u32 = {want}u;");
            assert!(src.contains(&decl), "{file}: {decl}");
            let halved = src.replace(&decl, &format!("const {name}: u32 = {}u;", want / 2));
            for (entry, size) in workgroup_sizes(&halved, &path) {
                assert_eq!(size, [want / 2, 1, 1], "{file}: {entry} names {name}");
            }
        }
    }
}

#[test]
fn the_validator_rejects_a_broken_kernel() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.wgsl");
    let src = std::fs::read_to_string(shader_dir().join("eval.wgsl"))
        .unwrap()
        .replace("let g = geom(q, it.cell);", "let g = geom(q, it.cel);");
    std::fs::write(&bad, src).unwrap();
    assert!(validate(&bad).is_err());
}

/// (size, member offsets) of struct `name` in `module`, as naga lays it out.
fn reflect(module: &naga::Module, name: &str) -> Option<(usize, Vec<(String, usize)>)> {
    let (_, ty) = module
        .types
        .iter()
        .find(|(_, t)| t.name.as_deref() == Some(name))?;
    match &ty.inner {
        naga::TypeInner::Struct { members, span } => Some((
            *span as usize,
            members
                .iter()
                .map(|m| (m.name.clone().unwrap(), m.offset as usize))
                .collect(),
        )),
        _ => None,
    }
}

/// Compares every shared struct in `module` with the Rust layout (with `fit`, the fit
/// kernel's too); returns the mismatches.
fn layout_mismatches(module: &naga::Module, fit: bool) -> Vec<String> {
    let mut bad = Vec::new();
    let mut all = layout::layouts();
    if fit {
        all.extend(layout::fit_layouts());
    }
    for (name, size, fields) in all {
        let want: Vec<(String, usize)> = fields.iter().map(|(f, o)| (f.to_string(), *o)).collect();
        match reflect(module, name) {
            Some((s, got)) if s == size && got == want => {}
            Some((s, got)) => bad.push(format!(
                "{name}: WGSL {s} bytes {got:?}, Rust {size} bytes {want:?}"
            )),
            None => bad.push(format!("{name}: missing from the WGSL")),
        }
    }
    bad
}

#[test]
fn every_kernel_lays_out_the_shared_structs_as_the_host_writes_them() {
    for path in kernels() {
        let module = parse(&source(&path).unwrap(), &path).unwrap();
        let bad = layout_mismatches(&module, is_fit(&path));
        assert!(bad.is_empty(), "{}: {bad:#?}", path.display());
    }
}

#[test]
fn the_layout_check_catches_a_drifted_struct() {
    // A vec3 field is 16-byte aligned in WGSL but not in Rust: the check must see it.
    let src = common_wgsl().replacen(
        "    fx: f32,\n    fy: f32,\n    fz: f32,\n",
        "    f: vec3<f32>,\n",
        1,
    );
    assert_ne!(src, common_wgsl());
    let src = src
        .replace("q.fx, q.fy, q.fz", "q.f.x, q.f.y, q.f.z")
        .replace("q.fx = bitcast", "q.f.x = bitcast")
        .replace("q.fy = bitcast", "q.f.y = bitcast")
        .replace("q.fz = bitcast", "q.f.z = bitcast");
    let module = parse(&src, Path::new("drifted.wgsl")).unwrap();
    let bad = layout_mismatches(&module, false);
    assert_eq!(bad.len(), 1, "{bad:?}");
    assert!(bad[0].starts_with("GQuery"), "{bad:?}");
}

/// A kernel variant's full source (as the engine builds it) parses and validates with
/// core WebGPU capabilities.
fn validate_variant(src: &str, name: &str) -> Result<(), String> {
    let module = parse(src, Path::new(name))?;
    naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        naga::valid::Capabilities::empty(),
    )
    .validate(&module)
    .map(|_| ())
    .map_err(|e| format!("{e:?}"))
}

/// The grid walk as the engine compiles it, once per pass with the pass a constant.
#[test]
fn both_walk_passes_validate() {
    for emit in [false, true] {
        let src = linegs_gpu::engine::gpu::walk_source(emit);
        assert!(src.contains(&format!("let emit = {emit};")));
        assert!(!src.contains("= params.mode"));
        validate_variant(&src, "walk.wgsl").unwrap_or_else(|e| panic!("emit {emit}: {e}"));
    }
}

/// The evaluation kernel as the engine compiles it, once per mode with the mode a
/// constant: every variant validates, and the mode really is replaced.
#[test]
fn every_evaluation_mode_variant_validates() {
    for mode in [
        layout::MODE_STATS,
        layout::MODE_STATS_SIDES,
        layout::MODE_HIST,
        layout::MODE_BELOW,
        layout::MODE_MEMBERS,
    ] {
        let cover = mode == layout::MODE_STATS || mode == layout::MODE_STATS_SIDES;
        let src = linegs_gpu::engine::gpu::eval_source(mode, cover);
        assert!(src.contains(&format!("let mode = {mode}u;")));
        assert!(src.contains(&format!("let cover_on = {cover};")));
        assert!(!src.contains("= params.mode;") && !src.contains("= params.cover"));
        validate_variant(&src, "eval.wgsl").unwrap_or_else(|e| panic!("mode {mode}: {e}"));
    }
}

/// `walk.wgsl` writes each item as one vec4<u32> in `Item`'s field order.
#[test]
fn the_walk_writes_items_in_their_field_order() {
    use linegs_gpu::engine::gpu::layout::Item;
    assert_eq!(
        Item::FIELDS,
        [("query", 0), ("cell", 4), ("start", 8), ("count", 12)]
    );
    assert_eq!(std::mem::size_of::<Item>(), 16);
    let walk = std::fs::read_to_string(shader_dir().join("walk.wgsl")).unwrap();
    assert!(walk.contains("items[at] = vec4<u32>(qi, c, s, end - s);"));
}
