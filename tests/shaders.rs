//! Every kernel parses and validates with naga, without a GPU: a shader typo fails here,
//! not in a user's run.

use std::path::Path;

/// A kernel as the engine loads it: `common.wgsl` first (WGSL has no include).
fn source(path: &Path) -> Result<String, String> {
    let src = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(if path.file_name().is_some_and(|n| n == "common.wgsl") {
        src
    } else {
        linegs_gpu::engine::gpu::kernel_source(&src)
    })
}

fn validate(path: &Path) -> Result<naga::valid::ModuleInfo, String> {
    let src = source(path)?;
    let module = naga::front::wgsl::parse_str(&src)
        .map_err(|e| e.emit_to_string_with_path(&src, path.to_string_lossy().as_ref()))?;
    naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        // No subgroups, no f64, nothing beyond core WebGPU.
        naga::valid::Capabilities::empty(),
    )
    .validate(&module)
    .map_err(|e| e.emit_to_string_with_path(&src, path.to_string_lossy().as_ref()))
}

#[test]
fn every_shader_is_valid_wgsl() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("shaders");
    let mut names = Vec::new();
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "wgsl") {
            if let Err(e) = validate(&path) {
                panic!("{e}");
            }
            names.push(path.file_name().unwrap().to_string_lossy().into_owned());
        }
    }
    names.sort();
    assert_eq!(
        names,
        ["common.wgsl", "coverage.wgsl", "nearest.wgsl", "stats.wgsl"]
    );
}

#[test]
fn the_validator_rejects_a_broken_kernel() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.wgsl");
    let src =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("shaders/stats.wgsl"))
            .unwrap()
            .replace("let u = dot(w, it.d);", "let u = dot(w, it.dd);");
    std::fs::write(&bad, src).unwrap();
    assert!(validate(&bad).is_err());
}

#[test]
fn kernels_share_the_work_item_layout() {
    // The launchers upload one `Item` layout to all three kernels: it is defined once, in
    // common.wgsl, and is 48 bytes as the host writes it.
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("shaders");
    let item = |name: &str| {
        let src = source(&dir.join(name)).unwrap();
        let module = naga::front::wgsl::parse_str(&src).unwrap();
        let (_, ty) = module
            .types
            .iter()
            .find(|(_, t)| t.name.as_deref() == Some("Item"))
            .expect("struct Item");
        match &ty.inner {
            naga::TypeInner::Struct { members, span } => (
                members
                    .iter()
                    .map(|m| (m.name.clone().unwrap(), m.offset))
                    .collect::<Vec<_>>(),
                *span,
            ),
            _ => panic!("Item is not a struct"),
        }
    };
    let stats = item("stats.wgsl");
    assert_eq!(stats.1, 48);
    assert_eq!(stats, item("nearest.wgsl"));
    assert_eq!(stats, item("coverage.wgsl"));
}
