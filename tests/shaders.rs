//! Every kernel parses and validates with naga, without a GPU: a shader typo fails here,
//! not in a user's run. And every struct the host and the kernels share has, in naga's
//! reflection of each kernel, the offsets and size of the Rust struct the host writes.

use linegs_gpu::engine::gpu::{
    common_wgsl, kernel_source, kernel_specs, layout, list_kernel_source, KernelSpec, When,
};
use std::path::Path;

/// The first registered pipeline of the shader at `path`.
fn spec_of(path: &Path) -> Option<&'static KernelSpec> {
    let name = path.file_name()?.to_str()?;
    kernel_specs().find(|k| k.shader == name)
}

/// A kernel as the engine loads it (its registered source: the generated prelude and
/// `common.wgsl` first); the shared parts alone; any other file as a plain kernel.
fn source(path: &Path) -> Result<String, String> {
    if let Some(k) = spec_of(path) {
        return Ok((k.source)());
    }
    let src = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(if path.file_name().is_some_and(|n| n == "common.wgsl") {
        common_wgsl()
    } else if path.file_name().is_some_and(|n| n == "lists.wgsl") {
        list_kernel_source("")
    } else {
        kernel_source(&src)
    })
}

/// The kernels over the member lists run in f64 (with `lists.wgsl`, their shared part):
/// the kernels that need a capability (`SHADER_F64`), and those with the list frame.
fn is_fit(path: &Path) -> bool {
    path.file_name().is_some_and(|n| n == "lists.wgsl")
        || spec_of(path).is_some_and(|k| k.when == When::F64)
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
            "lists.wgsl",
            "members.wgsl",
            "records.wgsl",
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

/// Compares every shared struct in `module` with the Rust layout (with `fit`, the list
/// kernels' frame too); returns the mismatches.
fn layout_mismatches(module: &naga::Module, fit: bool) -> Vec<String> {
    layout_mismatches_of(module, fit, &[])
}

/// [`layout_mismatches`] and the kernel's own structs (`own`).
fn layout_mismatches_of(module: &naga::Module, fit: bool, own: &[layout::Layout]) -> Vec<String> {
    let mut bad = Vec::new();
    let mut all = layout::layouts();
    if fit {
        all.extend(layout::list_layouts());
    }
    all.extend_from_slice(own);
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
    // Each registered pipeline, its launcher's own structs included (the fit's `FitOut`,
    // the extent's `ExtentOut`).
    let mut own = 0;
    for k in kernel_specs() {
        let module = parse(&(k.source)(), Path::new(k.shader)).unwrap();
        let bad = layout_mismatches_of(&module, k.when == When::F64, k.structs);
        assert!(bad.is_empty(), "{} {}: {bad:#?}", k.name, k.entry);
        own += k.structs.len();
    }
    assert_eq!(own, 2, "FitOut and ExtentOut");
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

/// The registered pipeline named `name`'s source, as the engine compiles it.
fn source_of(name: &str) -> String {
    let k = kernel_specs().find(|k| k.name == name);
    (k.unwrap_or_else(|| panic!("no kernel {name}")).source)()
}

/// The grid walk as the engine compiles it, once per pass with the pass a constant.
#[test]
fn both_walk_passes_validate() {
    for (emit, name) in [(false, "walk count"), (true, "walk emit")] {
        let src = source_of(name);
        assert!(src.contains(&format!("let emit = {emit};")));
        assert!(!src.contains("= params.mode"));
        validate_variant(&src, "walk.wgsl").unwrap_or_else(|e| panic!("emit {emit}: {e}"));
    }
}

/// The evaluation kernel as the engine compiles it, once per mode with the mode a
/// constant: every variant validates, and the mode really is replaced.
#[test]
fn every_evaluation_mode_variant_validates() {
    let evals: Vec<String> = kernel_specs()
        .filter(|k| k.shader == "eval.wgsl")
        .map(|k| (k.source)())
        .collect();
    let variants = [
        (layout::MODE_STATS, false),
        (layout::MODE_STATS, true),
        (layout::MODE_STATS_SIDES, false),
        (layout::MODE_STATS_SIDES, true),
        (layout::MODE_HIST, false),
        (layout::MODE_BELOW, false),
        (layout::MODE_MEMBERS, false),
    ];
    assert_eq!(evals.len(), variants.len());
    for (mode, cover) in variants {
        let want = [
            format!("let mode = {mode}u;"),
            format!("let cover_on = {cover};"),
        ];
        let src = evals
            .iter()
            .find(|s| want.iter().all(|w| s.contains(w)))
            .unwrap_or_else(|| panic!("no evaluation variant {mode} {cover}"));
        assert!(!src.contains("= params.mode;") && !src.contains("= params.cover"));
        validate_variant(src, "eval.wgsl").unwrap_or_else(|e| panic!("mode {mode}: {e}"));
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

/// Every pipeline of the kernel registry, as the engine compiles it, validates (with f64
/// exactly where the registry compiles it only on an f64 device); every shader under
/// `shaders/` but the shared parts is some kernel's; no two pipelines share a name and
/// entry point.
#[test]
fn every_registered_kernel_validates_and_every_shader_is_registered() {
    use linegs_gpu::engine::gpu::{kernel_specs, When};
    let mut seen = std::collections::BTreeSet::new();
    let mut shaders = std::collections::BTreeSet::new();
    for k in kernel_specs() {
        assert!(
            seen.insert((k.name, k.entry)),
            "{} {} twice",
            k.name,
            k.entry
        );
        shaders.insert(k.shader.to_string());
        let src = (k.source)();
        let path = Path::new(k.shader);
        let module = parse(&src, path).unwrap_or_else(|e| panic!("{e}"));
        let caps = if k.when == When::F64 {
            naga::valid::Capabilities::FLOAT64
        } else {
            naga::valid::Capabilities::empty()
        };
        naga::valid::Validator::new(naga::valid::ValidationFlags::all(), caps)
            .validate(&module)
            .unwrap_or_else(|e| panic!("{} {}: {e:?}", k.name, k.entry));
        assert!(
            module.entry_points.iter().any(|e| e.name == k.entry),
            "{}: no entry point {}",
            k.shader,
            k.entry
        );
    }
    let files: std::collections::BTreeSet<String> = kernels()
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .filter(|n| n != "common.wgsl" && n != "lists.wgsl")
        .collect();
    assert_eq!(files, shaders);
}

/// A kernel is a unit: its shader is loaded by its own launcher alone
/// (`src/engine/gpu/kernels/<name>.rs`, named after it), and the launcher's pipelines are
/// in the registry, which is the only other file of `src/` that names the launcher.
#[test]
fn each_shader_is_loaded_by_its_own_launcher_only() {
    let sources = rust_sources();
    let registry = "src/engine/gpu/kernels/mod.rs";
    let reg = &sources.iter().find(|(p, _)| p == registry).unwrap().1;
    for path in kernels() {
        let name = path.file_stem().unwrap().to_string_lossy().into_owned();
        let file = format!("{name}.wgsl");
        let loads: Vec<&str> = sources
            .iter()
            .filter(|(_, t)| t.contains(&format!("shaders/{file}\")")))
            .map(|(p, _)| p.as_str())
            .collect();
        let want = match name.as_str() {
            // The shared parts: assembled into every kernel's source by the registry.
            "common" | "lists" => registry.to_string(),
            _ => format!("src/engine/gpu/kernels/{name}.rs"),
        };
        assert_eq!(loads, [want.as_str()], "{file} is loaded by");
        if !matches!(name.as_str(), "common" | "lists") {
            assert!(
                reg.contains(&format!("mod {name};"))
                    && reg.contains(&format!("&{name}::KERNELS,")),
                "{name}: one `mod` and one registry line in {registry}"
            );
            let naming: Vec<&str> = sources
                .iter()
                .filter(|(_, t)| {
                    t.contains(&format!("kernels::{name}::")) || t.contains(&format!("mod {name};"))
                })
                .map(|(p, _)| p.as_str())
                .filter(|p| p.starts_with("src/engine/gpu/"))
                .collect();
            assert_eq!(naming, [registry], "{name}: the launcher is named by");
        }
    }
}

/// The code of a source file: the lines before its `#[cfg(test)]` module, each without
/// its `//` comment.
fn code_of(text: &str) -> Vec<&str> {
    text.lines()
        .take_while(|l| !l.trim_start().starts_with("#[cfg(test)]"))
        .map(|l| l.find("//").map_or(l, |k| &l[..k]))
        .collect()
}

/// Every `.rs` file under `src/`, as (path from the crate root, text).
fn rust_sources() -> Vec<(String, String)> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut sources = Vec::new();
    let mut stack = vec![root.join("src")];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                let text = std::fs::read_to_string(&p).unwrap();
                let rel = p.strip_prefix(root).unwrap().to_string_lossy();
                sources.push((rel.replace('\\', "/"), text));
            }
        }
    }
    sources.sort();
    sources
}

/// Whether `code` names `path` as a whole path segment (`kernels::fit`, not
/// `kernels::fit_x`).
fn names(code: &str, path: &str) -> bool {
    code.match_indices(path).any(|(at, _)| {
        let before = code[..at].chars().next_back();
        let after = code[at + path.len()..].chars().next();
        !before.is_some_and(|c| c.is_alphanumeric() || c == '_')
            && !after.is_some_and(|c| c.is_alphanumeric() || c == '_')
    })
}

/// A kernel is reached only through the registry (`kernels/mod.rs`): no file outside
/// `src/engine/gpu/kernels/` names a launcher, the registry re-exports nothing of one,
/// and every item of a launcher that is visible outside `kernels/` (plain `pub`) is a
/// static the registry lists (its `KERNELS`, its stages, its routes); everything else
/// of a launcher is `pub(super)` or private, so that the compiler keeps the GPU engine,
/// the batches, the sizes and the buffers from calling into it. Adding a kernel then
/// changes no file but its own two and the registry.
#[test]
fn a_launcher_is_reached_only_through_the_registry() {
    let sources = rust_sources();
    let dir = "src/engine/gpu/kernels/";
    let registry = format!("{dir}mod.rs");
    let reg = code_of(&sources.iter().find(|(p, _)| *p == registry).unwrap().1).join("\n");
    let launchers: Vec<(String, &str)> = sources
        .iter()
        .filter(|(p, _)| p.starts_with(dir) && *p != registry)
        .map(|(p, t)| {
            (
                p[dir.len()..].trim_end_matches(".rs").to_string(),
                t.as_str(),
            )
        })
        .collect();
    assert!(launchers.len() >= 10, "{launchers:?}");
    let mut bad = Vec::new();
    for (path, text) in sources.iter().filter(|(p, _)| !p.starts_with(dir)) {
        for (n, line) in code_of(text).iter().enumerate() {
            for (name, _) in &launchers {
                if names(line, &format!("kernels::{name}")) {
                    bad.push(format!("{path}:{}: names the launcher {name}", n + 1));
                }
            }
        }
    }
    for line in reg
        .lines()
        .filter(|l| l.trim_start().starts_with("pub use"))
    {
        bad.push(format!("{registry}: re-exports `{}`", line.trim()));
    }
    for (name, text) in &launchers {
        for (n, line) in code_of(text).iter().enumerate() {
            let Some(rest) = line.trim_start().strip_prefix("pub ") else {
                continue;
            };
            let item = rest
                .strip_prefix("static ")
                .map(|r| r.split(|c: char| !(c.is_alphanumeric() || c == '_')).next());
            match item.flatten() {
                Some(item) if names(&reg, &format!("&{name}::{item}")) => {}
                _ => bad.push(format!(
                    "{dir}{name}.rs:{}: visible outside kernels/ and not in the registry: {}",
                    n + 1,
                    line.trim()
                )),
            }
        }
    }
    assert!(bad.is_empty(), "{bad:#?}");
}

/// The stages of each kind of batch are the registry's (`kernels::STAGES`), in its
/// order, each with the buffers its launcher declares: `batch.rs` records exactly what
/// `batch_stages` lists (both iterate the same sequence), and a rerun leaves out the
/// count walk and its scan.
#[test]
fn each_kind_of_batch_records_the_registrys_stages_in_order() {
    use linegs_gpu::engine::gpu::batch_stages;
    let show = |rerun: bool| -> Vec<String> {
        batch_stages(rerun)
            .into_iter()
            .map(|(kind, stages)| {
                let stages: Vec<String> = stages
                    .iter()
                    .map(|(s, own)| match own.is_empty() {
                        true => s.to_string(),
                        false => format!("{s} [{}]", own.join(", ")),
                    })
                    .collect();
                format!("{kind}: {}", stages.join(" > "))
            })
            .collect()
    };
    let head = "walk count > scan > args > walk emit > eval";
    let lists = format!("{head} > members [mscan] > reduce > list [fitq, fitout]");
    assert_eq!(
        show(false),
        [
            format!("stats: {head} > reduce"),
            format!("stats sides cover: {head} > reduce"),
            format!("nearest: {head} > cut > reduce"),
            format!("members: {head} > members [mscan] > reduce > records [records]"),
            format!("list extent: {lists}"),
            format!("list fit: {lists}"),
        ]
    );
    let first = show(false);
    for (again, first) in show(true).iter().zip(&first) {
        assert_eq!(*again, first.replacen("walk count > scan > ", "", 1));
    }
}
