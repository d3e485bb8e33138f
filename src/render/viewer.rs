//! A self-contained HTML viewer: one file, no network access. The Gaussian centres
//! (subsampled beyond a limit, with a note) and each segment set are layers that can be
//! toggled from a legend that gives their counts; drag orbits, shift-drag pans, the wheel
//! zooms, and the first view (and double-click) frames the segments. Layers are drawn in
//! the order given, the last on top ([`viewer_layers`] puts the refined lines there).
//! Canvas 2D rather than WebGL, so it works where WebGL is off (remote desktops, headless
//! browsers without a GPU).

use std::fmt::Write as _;

use glam::DVec3;

use super::plot::xml_escape;
use super::{framing_box, Layer, Panel};
use crate::geom::Segment;

/// Colour of the input segments in every picture and viewer.
pub const INPUT_COLOR: [u8; 3] = [220, 60, 40];
/// Colour of the refined segments.
pub const REFINED_COLOR: [u8; 3] = [30, 100, 230];
/// Colour of ground-truth edges.
pub const GT_COLOR: [u8; 3] = [40, 170, 60];

/// The viewer's segment layers in drawing order, the last on top: the input at the
/// bottom, then the ground truth, then the refined lines, so that the result is never
/// hidden under the sets it is compared with.
pub fn viewer_layers<'a>(
    input: &'a [Segment],
    refined: Option<&'a [Segment]>,
    ground_truth: Option<&'a [Segment]>,
) -> Vec<Layer<'a>> {
    let mut layers = vec![Layer {
        name: "input segments",
        segments: input,
        color: INPUT_COLOR,
    }];
    if let Some(g) = ground_truth {
        layers.push(Layer {
            name: "ground truth",
            segments: g,
            color: GT_COLOR,
        });
    }
    if let Some(r) = refined {
        layers.push(Layer {
            name: "refined segments",
            segments: r,
            color: REFINED_COLOR,
        });
    }
    layers
}

/// Standard base64 (RFC 4648, with padding); the browser decodes it with `atob`.
pub fn base64(bytes: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for c in bytes.chunks(3) {
        let n = (c[0] as u32) << 16
            | (*c.get(1).unwrap_or(&0) as u32) << 8
            | *c.get(2).unwrap_or(&0) as u32;
        out.push(A[(n >> 18) as usize & 63] as char);
        out.push(A[(n >> 12) as usize & 63] as char);
        out.push(if c.len() > 1 {
            A[(n >> 6) as usize & 63] as char
        } else {
            '='
        });
        out.push(if c.len() > 2 {
            A[n as usize & 63] as char
        } else {
            '='
        });
    }
    out
}

/// Little-endian f32 bytes of `values` (the byte order of every browser's typed arrays).
fn f32_bytes(values: impl Iterator<Item = f32>) -> Vec<u8> {
    values.flat_map(|v| v.to_le_bytes()).collect()
}

/// Indices of at most `max` of `n` items, evenly spread so a subsample keeps the shape.
fn subsample(n: usize, max: usize) -> Vec<usize> {
    if n <= max {
        (0..n).collect()
    } else {
        (0..max)
            .map(|i| (i as u128 * n as u128 / max as u128) as usize)
            .collect()
    }
}

/// JSON text that is safe inside a `<script>` element: `</` cannot end it early.
fn script_json(v: &serde_json::Value) -> String {
    v.to_string()
        .replace("</", "<\\/")
        .replace("<!--", "<\\!--")
}

/// The viewer as one HTML document. Coordinates are sent relative to the centre of the
/// framed box, so f32 keeps its precision for scenes far from the origin.
pub fn viewer_html(
    points: &[[f32; 3]],
    layers: &[Layer],
    title: &str,
    max_points: usize,
) -> String {
    let finite: Vec<[f32; 3]> = points
        .iter()
        .copied()
        .filter(|p| p.iter().all(|c| c.is_finite()))
        .collect();
    let panel = Panel {
        title,
        layers: layers.to_vec(),
        metrics: vec![],
    };
    let (lo, hi) = framing_box(&finite, std::slice::from_ref(&panel));
    let center = (lo + hi) * 0.5;
    let radius = ((hi - lo).length() * 0.5).max(1e-9);
    let rel = |p: DVec3| (p - center).to_array().map(|c| c as f32);

    let keep = subsample(finite.len(), max_points);
    let pts = f32_bytes(
        keep.iter()
            .flat_map(|&i| rel(DVec3::from_array(finite[i].map(|c| c as f64)))),
    );
    let note = if keep.len() < finite.len() {
        format!(
            "showing {} of {} Gaussian centers (evenly subsampled)",
            keep.len(),
            finite.len()
        )
    } else {
        String::new()
    };
    let layer_json: Vec<serde_json::Value> = layers
        .iter()
        .map(|l| {
            let segs: Vec<_> = l
                .segments
                .iter()
                .filter(|s| s.p1.is_finite() && s.p2.is_finite())
                .collect();
            let data = f32_bytes(
                segs.iter()
                    .flat_map(|s| rel(s.p1).into_iter().chain(rel(s.p2))),
            );
            serde_json::json!({
                "name": l.name,
                "color": format!("rgb({},{},{})", l.color[0], l.color[1], l.color[2]),
                "count": segs.len(),
                "data": base64(&data),
            })
        })
        .collect();
    let data = serde_json::json!({
        "title": title,
        "radius": radius,
        "center": center.to_array(),
        "points": base64(&pts),
        "pointCount": keep.len(),
        "totalPoints": finite.len(),
        "note": note,
        "layers": layer_json,
    });

    let mut html = String::new();
    let _ = write!(
        html,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n\
         <meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n\
         <title>{}</title>\n<style>{STYLE}</style>\n</head>\n<body>\n\
         <canvas id=\"view\"></canvas>\n<div id=\"panel\"><div id=\"title\"></div>\
         <div id=\"layers\"></div><div id=\"note\"></div>\
         <div id=\"help\">drag: orbit &middot; shift+drag: pan &middot; wheel: zoom &middot; double-click: reset</div></div>\n\
         <script type=\"application/json\" id=\"data\">{}</script>\n<script>{SCRIPT}</script>\n</body>\n</html>\n",
        xml_escape(title),
        script_json(&data)
    );
    html
}

const STYLE: &str = r##"
html, body { margin: 0; height: 100%; overflow: hidden; background: #fff; font: 14px sans-serif; color: #222; }
canvas { display: block; width: 100vw; height: 100vh; cursor: grab; }
#panel { position: absolute; top: 10px; left: 10px; background: rgba(255,255,255,0.9); border: 1px solid #ccc;
         border-radius: 4px; padding: 8px 10px; max-width: 40vw; }
#title { font-weight: bold; margin-bottom: 6px; }
#layers label { display: block; margin: 2px 0; white-space: nowrap; }
.swatch { display: inline-block; width: 22px; height: 4px; vertical-align: middle; margin: 0 6px 0 2px; }
#note { color: #a33; margin-top: 6px; }
#note:empty { display: none; }
#help { color: #777; font-size: 12px; margin-top: 6px; }
"##;

/// The viewer's code: decodes the embedded data, then draws points (a density image,
/// like the PNG pictures) and segments (canvas paths) through an orbiting camera.
const SCRIPT: &str = r##"
"use strict";
const D = JSON.parse(document.getElementById("data").textContent);
function decode(b64) {
  const s = atob(b64), u = new Uint8Array(s.length);
  for (let i = 0; i < s.length; i++) u[i] = s.charCodeAt(i);
  return new Float32Array(u.buffer);
}
const P = decode(D.points);
const layers = D.layers.map(l => ({ name: l.name, color: l.color, count: l.count, seg: decode(l.data), on: true }));
const showPoints = { on: true };
const canvas = document.getElementById("view"), ctx = canvas.getContext("2d");
const R = D.radius;
let yaw = -Math.PI / 3, pitch = 0.5, zoom = 1, panX = 0, panY = 0;

document.getElementById("title").textContent = D.title;
document.getElementById("note").textContent = D.note;
const box = document.getElementById("layers");
function addToggle(label, color, state) {
  const l = document.createElement("label"), c = document.createElement("input"), s = document.createElement("span");
  c.type = "checkbox"; c.checked = true;
  c.addEventListener("change", () => { state.on = c.checked; draw(); });
  s.className = "swatch"; s.style.background = color;
  l.append(c, s, document.createTextNode(label));
  box.append(l);
}
// The legend lists the layers top first, as they are stacked; the points lie below all.
for (const l of layers.slice().reverse()) addToggle(l.name + " (" + l.count + ")", l.color, l);
addToggle("Gaussian centers (" + (D.pointCount < D.totalPoints ? D.pointCount + " of " + D.totalPoints : D.pointCount) + ")", "#888", showPoints);

function camera() {
  const cy = Math.cos(yaw), sy = Math.sin(yaw), cp = Math.cos(pitch), sp = Math.sin(pitch);
  const back = [cp * cy, cp * sy, sp];        // from the scene centre towards the camera
  const right = [-sy, cy, 0];
  const up = [-sp * cy, -sp * sy, cp];
  const dist = 3 * R;
  const W = canvas.width, H = canvas.height;
  // At zoom 1 the bounding sphere fills 90 % of the shorter side.
  const f = 0.45 * Math.min(W, H) * zoom * Math.sqrt(dist * dist - R * R) / R;
  return { back, right, up, dist, f, cx: W / 2 + panX, cy: H / 2 + panY, near: 1e-3 * dist };
}

function size() {
  const dpr = window.devicePixelRatio || 1;
  const W = Math.max(1, Math.round(canvas.clientWidth * dpr)), H = Math.max(1, Math.round(canvas.clientHeight * dpr));
  if (canvas.width !== W || canvas.height !== H) { canvas.width = W; canvas.height = H; }
}

// Frames the segments of every layer (the points when there are none) in 90 % of the
// window: screen offsets from the centre scale linearly with the zoom, so one projection
// at zoom 1 gives the zoom and pan that fit.
function fit() {
  size();
  zoom = 1; panX = 0; panY = 0;
  const c = camera();
  let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity;
  const visit = (x, y, z) => {
    const d = c.dist - (x * c.back[0] + y * c.back[1] + z * c.back[2]);
    if (!(d > c.near)) return;
    const s = c.f / d;
    const sx = (x * c.right[0] + y * c.right[1] + z * c.right[2]) * s;
    const sy = -(x * c.up[0] + y * c.up[1] + z * c.up[2]) * s;
    x0 = Math.min(x0, sx); x1 = Math.max(x1, sx); y0 = Math.min(y0, sy); y1 = Math.max(y1, sy);
  };
  for (const l of layers) for (let i = 0; i < l.seg.length; i += 3) visit(l.seg[i], l.seg[i + 1], l.seg[i + 2]);
  if (!(x1 >= x0)) {
    const step = 3 * Math.max(1, Math.floor(P.length / 3 / 20000));
    for (let i = 0; i + 2 < P.length; i += step) visit(P[i], P[i + 1], P[i + 2]);
  }
  if (!(x1 >= x0)) return;
  const k = 0.9 * Math.min(canvas.width / Math.max(x1 - x0, 1e-9), canvas.height / Math.max(y1 - y0, 1e-9));
  zoom = Math.min(k, 1e6); panX = -0.5 * (x0 + x1) * zoom; panY = -0.5 * (y0 + y1) * zoom;
}

function draw() {
  size();
  const dpr = window.devicePixelRatio || 1;
  const W = canvas.width, H = canvas.height;
  const c = camera();
  const [r0, r1, r2] = c.right, [u0, u1, u2] = c.up, [b0, b1, b2] = c.back;
  const img = ctx.createImageData(W, H), px = img.data;
  if (showPoints.on && P.length) {
    const count = new Float32Array(W * H);
    for (let i = 0; i < P.length; i += 3) {
      const x = P[i], y = P[i + 1], z = P[i + 2];
      const d = c.dist - (x * b0 + y * b1 + z * b2);
      if (d <= c.near) continue;
      const s = c.f / d;
      const sx = Math.floor(c.cx + (x * r0 + y * r1 + z * r2) * s);
      const sy = Math.floor(c.cy - (x * u0 + y * u1 + z * u2) * s);
      if (sx >= 0 && sy >= 0 && sx < W && sy < H) count[sy * W + sx] += 1;
    }
    const gain = Math.min(0.35, Math.max(0.05, 0.3 * W * H / (P.length / 3)));
    for (let i = 0; i < W * H; i++) {
      const a = count[i] > 0 ? 1 - Math.exp(-gain * count[i]) : 0;
      const g = Math.round(255 - a * 160);
      px[4 * i] = g; px[4 * i + 1] = g; px[4 * i + 2] = g; px[4 * i + 3] = 255;
    }
  } else {
    for (let i = 0; i < W * H; i++) { px[4 * i] = px[4 * i + 1] = px[4 * i + 2] = px[4 * i + 3] = 255; }
  }
  ctx.putImageData(img, 0, 0);
  ctx.lineWidth = 1.6 * dpr; ctx.lineCap = "round";
  for (const l of layers) {
    if (!l.on) continue;
    ctx.strokeStyle = l.color;
    ctx.beginPath();
    const S = l.seg;
    for (let i = 0; i < S.length; i += 6) {
      let a = [S[i], S[i + 1], S[i + 2]], b = [S[i + 3], S[i + 4], S[i + 5]];
      let da = c.dist - (a[0] * b0 + a[1] * b1 + a[2] * b2), db = c.dist - (b[0] * b0 + b[1] * b1 + b[2] * b2);
      const near = 2 * c.near;
      if (da <= near && db <= near) continue;
      // Cut the part behind the camera, which would otherwise project mirrored.
      if (da < near) { const t = (db - near) / (db - da); a = a.map((v, k) => b[k] + (v - b[k]) * t); da = near; }
      if (db < near) { const t = (da - near) / (da - db); b = b.map((v, k) => a[k] + (v - a[k]) * t); db = near; }
      const sa = c.f / da, sb = c.f / db;
      ctx.moveTo(c.cx + (a[0] * r0 + a[1] * r1 + a[2] * r2) * sa, c.cy - (a[0] * u0 + a[1] * u1 + a[2] * u2) * sa);
      ctx.lineTo(c.cx + (b[0] * r0 + b[1] * r1 + b[2] * r2) * sb, c.cy - (b[0] * u0 + b[1] * u1 + b[2] * u2) * sb);
    }
    ctx.stroke();
  }
}

let pending = false;
function redraw() { if (!pending) { pending = true; requestAnimationFrame(() => { pending = false; draw(); }); } }
let drag = null;
canvas.addEventListener("mousedown", e => { drag = { x: e.clientX, y: e.clientY, pan: e.shiftKey || e.button !== 0 }; canvas.style.cursor = "grabbing"; });
window.addEventListener("mouseup", () => { drag = null; canvas.style.cursor = "grab"; });
window.addEventListener("mousemove", e => {
  if (!drag) return;
  const dx = e.clientX - drag.x, dy = e.clientY - drag.y, dpr = window.devicePixelRatio || 1;
  drag.x = e.clientX; drag.y = e.clientY;
  if (drag.pan) { panX += dx * dpr; panY += dy * dpr; }
  else { yaw -= dx * 0.01; pitch = Math.max(-1.55, Math.min(1.55, pitch + dy * 0.01)); }
  redraw();
});
canvas.addEventListener("wheel", e => { e.preventDefault(); zoom *= Math.exp(-e.deltaY * 0.001); redraw(); }, { passive: false });
canvas.addEventListener("contextmenu", e => e.preventDefault());
canvas.addEventListener("dblclick", () => { yaw = -Math.PI / 3; pitch = 0.5; fit(); redraw(); });
window.addEventListener("resize", redraw);
fit();
draw();
"##;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_refined_lines_are_drawn_last_and_listed_first() {
        let s = [Segment::from_arrays([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])];
        let names = |l: Vec<Layer>| l.iter().map(|l| l.name.to_string()).collect::<Vec<_>>();
        assert_eq!(
            names(viewer_layers(&s, Some(&s), Some(&s))),
            ["input segments", "ground truth", "refined segments"]
        );
        assert_eq!(
            names(viewer_layers(&s, Some(&s), None)),
            ["input segments", "refined segments"]
        );
        // The page keeps that order (the script draws in it) and says so in the legend.
        let html = viewer_html(&[], &viewer_layers(&s, Some(&s), Some(&s)), "t", 10);
        let at = |n: &str| html.find(&format!("\"name\":\"{n}\"")).unwrap();
        assert!(at("input segments") < at("ground truth"));
        assert!(at("ground truth") < at("refined segments"));
        assert!(html.contains("layers.slice().reverse()"));
    }

    #[test]
    fn base64_matches_rfc_4648_vectors() {
        for (raw, enc) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(raw.as_bytes()), enc);
        }
        assert_eq!(base64(&[0xfb, 0xff]), "+/8=");
    }

    #[test]
    fn subsampling_is_even_and_bounded() {
        assert_eq!(subsample(3, 10), vec![0, 1, 2]);
        assert_eq!(subsample(10, 4), vec![0, 2, 5, 7]);
        assert!(subsample(5, 0).is_empty());
    }

    #[test]
    fn html_embeds_the_data_and_reaches_for_nothing_outside() {
        let segs = [Segment::from_arrays([0.0, 0.0, 0.0], [2.0, 0.0, 0.0])];
        let points = [[1.0f32, 0.0, 0.0], [f32::NAN, 0.0, 0.0], [1.0, 0.5, 0.0]];
        let layers = [Layer {
            name: "refined </script><b>",
            segments: &segs,
            color: [33, 102, 172],
        }];
        let html = viewer_html(&points, &layers, "scene <1> & co", 10);
        assert!(!html.contains("http://") && !html.contains("https://"));
        assert!(
            !html.contains(" src=") && !html.contains(" href="),
            "no external resources"
        );
        assert!(html.contains("<title>scene &lt;1&gt; &amp; co</title>"));
        // Exactly our two script elements: the layer name cannot close one early.
        assert_eq!(html.matches("</script>").count(), 2);
        assert!(html.contains(r#"refined <\/script><b>"#));
        // The framed box is [0, 2] x [0, 0.5] x [0, 0] padded by 1 %: its centre is
        // (1, 0.25, 0), so the segment is sent as (-1, -0.25, 0) - (1, -0.25, 0).
        let seg = f32_bytes([-1.0f32, -0.25, 0.0, 1.0, -0.25, 0.0].into_iter());
        assert!(html.contains(&base64(&seg)), "segment data missing");
        // The NaN point is dropped; the two others are sent relative to the centre.
        let pts = f32_bytes([0.0f32, -0.25, 0.0, 0.0, 0.25, 0.0].into_iter());
        assert!(html.contains(&format!("\"points\":\"{}\"", base64(&pts))));
        assert!(html.contains("\"note\":\"\""));
        assert!(html.contains("rgb(33,102,172)"));
    }

    #[test]
    fn a_note_says_when_points_were_subsampled() {
        let points: Vec<[f32; 3]> = (0..1000).map(|i| [i as f32, 0.0, 0.0]).collect();
        let html = viewer_html(&points, &[], "many", 100);
        assert!(html.contains("showing 100 of 1000 Gaussian centers"));
        assert!(html.contains("\"pointCount\":100"));
        // 100 points x 12 bytes = 1200 bytes = 1600 base64 characters.
        let start = html.find("\"points\":\"").unwrap() + 10;
        let len = html[start..].find('"').unwrap();
        assert_eq!(len, 1600);
    }
}
