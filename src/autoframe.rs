//! The automatic frame: when the lines (COLMAP frame) and the Gaussians disagree
//! ([`crate::frames`]), the normalizations the usual trainers apply to the COLMAP model
//! they were given are recomputed from that model, and the one under which the lines find
//! their Gaussians is taken.
//!
//! - gsplat (`examples/datasets/colmap.py` with `normalize_world_space`, its
//!   `normalize.py`): `T1 = similarity_from_cameras` (the mean camera up turned to +z,
//!   the median of the points of the cameras' axes nearest the origin moved to the origin,
//!   scaled by 1 / the median camera distance), then `T2 = align_principal_axes` of the
//!   sparse points mapped by `T1` (median centre, the covariance's eigenvectors, largest
//!   first, as rows), then a turn about x when the points' median height is above their
//!   mean. numpy's eigenvectors have no fixed sign, so the four proper sign choices of
//!   `T2` are candidates (the turn about x is one of them), and `T1` alone (gsplat without
//!   sparse points).
//! - nerfstudio's COLMAP dataparser (defaults: `orientation_method up`, `center_method
//!   poses`, `auto_scale_poses`): the OpenCV cameras turned to OpenGL axes, the world
//!   turned so that COLMAP's -y is +z (`applied_transform`), the mean camera up turned to
//!   +z about the mean camera centre, scaled by 1 / the largest camera coordinate.
//!
//! Each candidate maps the Gaussians back into the COLMAP frame (its inverse) and is
//! judged by the frame check at the run's radius; the one with the most segments near
//! Gaussians wins when its verdict is [`FrameVerdict::Same`]. Its residual is the median,
//! over the segments with Gaussians near them, of the RMS distance of those Gaussians to
//! the segment's line (scene units of the lines).

use std::sync::Arc;

use glam::{DMat3, DMat4, DVec3};

use crate::engine::cpu::CpuEngine;
use crate::engine::{Engine, EngineError, Query, Want};
use crate::frames::{check_frames, FrameCheck, FrameVerdict};
use crate::geom::Segment;
use crate::index::{Grid, WorkingSet};
use crate::io::ColmapModel;

/// A normalization a trainer applies: `to_model` maps COLMAP points into the frame the
/// model was trained in.
#[derive(Clone, Debug, PartialEq)]
pub struct Normalization {
    pub name: String,
    pub to_model: DMat4,
}

impl Normalization {
    /// The map of the model's Gaussians into the COLMAP frame of the lines.
    pub fn to_colmap(&self) -> DMat4 {
        self.to_model.inverse()
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    // numpy: the mean of the two middle values for an even count.
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

fn median3(v: &[DVec3]) -> DVec3 {
    DVec3::new(
        median(v.iter().map(|p| p.x).collect()),
        median(v.iter().map(|p| p.y).collect()),
        median(v.iter().map(|p| p.z).collect()),
    )
}

fn rt(r: DMat3, t: DVec3) -> DMat4 {
    let mut m = DMat4::from_mat3(r);
    m.w_axis = t.extend(1.0);
    m
}

fn skew(v: DVec3) -> DMat3 {
    // Columns of [[0, -z, y], [z, 0, -x], [-y, x, 0]].
    DMat3::from_cols(
        DVec3::new(0.0, v.z, -v.y),
        DVec3::new(-v.z, 0.0, v.x),
        DVec3::new(v.y, -v.x, 0.0),
    )
}

/// gsplat's `similarity_from_cameras(c2w)` (centre `focus`, median scaling).
pub fn similarity_from_cameras(c2w: &[DMat4]) -> DMat4 {
    let n = c2w.len() as f64;
    let up_cam = DVec3::new(0.0, -1.0, 0.0);
    let world_up = c2w
        .iter()
        .map(|m| DMat3::from_mat4(*m) * up_cam)
        .fold(DVec3::ZERO, |a, b| a + b)
        / n;
    let world_up = world_up.normalize();
    let c = up_cam.dot(world_up);
    let cross = world_up.cross(up_cam);
    let k = skew(cross);
    let r_align = if c > -1.0 {
        DMat3::IDENTITY + k + (k * k) * (1.0 / (1.0 + c))
    } else {
        DMat3::from_diagonal(DVec3::new(-1.0, 1.0, 1.0))
    };
    let nearest: Vec<DVec3> = c2w
        .iter()
        .map(|m| {
            let r = r_align * DMat3::from_mat4(*m);
            let fwd = r * DVec3::Z;
            let t = r_align * m.w_axis.truncate();
            t + fwd * fwd.dot(-t)
        })
        .collect();
    let translate = -median3(&nearest);
    let dist: Vec<f64> = c2w
        .iter()
        .map(|m| (r_align * m.w_axis.truncate() + translate).length())
        .collect();
    let scale = 1.0 / median(dist);
    DMat4::from_scale(DVec3::splat(scale)) * rt(r_align, translate)
}

/// Eigenvalues and unit eigenvectors (columns) of a symmetric 3x3 matrix (Jacobi).
pub fn symmetric_eigen(m: DMat3) -> (DVec3, DMat3) {
    let mut a = m.to_cols_array_2d(); // a[col][row], symmetric anyway
    let mut v = DMat3::IDENTITY.to_cols_array_2d();
    for _ in 0..64 {
        let off = a[0][1].abs() + a[0][2].abs() + a[1][2].abs();
        if off < 1e-300 {
            break;
        }
        for (p, q) in [(0usize, 1usize), (0, 2), (1, 2)] {
            if a[p][q].abs() < 1e-300 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let t = if theta == 0.0 { 1.0 } else { t };
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            // a = J^T a J with the rotation J in the (p, q) plane.
            for ak in a.iter_mut() {
                let (akp, akq) = (ak[p], ak[q]);
                ak[p] = c * akp - s * akq;
                ak[q] = s * akp + c * akq;
            }
            let (ap, aq) = (a[p], a[q]);
            a[p] = std::array::from_fn(|k| c * ap[k] - s * aq[k]);
            a[q] = std::array::from_fn(|k| s * ap[k] + c * aq[k]);
            for row in &mut v {
                let (vp, vq) = (row[p], row[q]);
                row[p] = c * vp - s * vq;
                row[q] = s * vp + c * vq;
            }
        }
    }
    // v[row][col] as built: transpose into columns.
    let vecs = DMat3::from_cols_array_2d(&v).transpose();
    (DVec3::new(a[0][0], a[1][1], a[2][2]), vecs)
}

/// gsplat's `align_principal_axes(points)` with the eigenvectors' signs `signs` (each
/// +-1, an even number of -1), before its determinant fix.
fn principal_axes(points: &[DVec3], signs: DVec3) -> DMat4 {
    let centroid = median3(points);
    let n = points.len() as f64;
    let mean = points.iter().fold(DVec3::ZERO, |a, p| a + *p) / n;
    let mut cov = DMat3::ZERO;
    for p in points {
        let d = *p - mean;
        cov += DMat3::from_cols(d * d.x, d * d.y, d * d.z);
    }
    let cov = cov * (1.0 / (n - 1.0).max(1.0));
    let (vals, vecs) = symmetric_eigen(cov);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| vals[b].total_cmp(&vals[a]));
    let mut cols = [
        vecs.col(order[0]) * signs.x,
        vecs.col(order[1]) * signs.y,
        vecs.col(order[2]) * signs.z,
    ];
    if DMat3::from_cols(cols[0], cols[1], cols[2]).determinant() < 0.0 {
        cols[0] = -cols[0];
    }
    let rotation = DMat3::from_cols(cols[0], cols[1], cols[2]).transpose();
    rt(rotation, -(rotation * centroid))
}

/// The candidates for a gsplat model trained with `normalize_world_space` on `m`.
pub fn gsplat_normalizations(m: &ColmapModel) -> Vec<Normalization> {
    if m.images.is_empty() {
        return Vec::new();
    }
    let c2w: Vec<DMat4> = m.images.iter().map(|i| i.camera_to_world()).collect();
    let t1 = similarity_from_cameras(&c2w);
    let mut out = vec![Normalization {
        name: "gsplat normalize_world_space, cameras only (similarity_from_cameras)".into(),
        to_model: t1,
    }];
    if m.points.len() < 3 {
        return out;
    }
    // gsplat reads the points as float32.
    let pts: Vec<DVec3> = m
        .points
        .iter()
        .map(|p| {
            let f = p.xyz.map(|x| x as f32 as f64);
            t1.transform_point3(DVec3::from_array(f))
        })
        .collect();
    for (k, signs) in [
        DVec3::new(1.0, 1.0, 1.0),
        DVec3::new(-1.0, -1.0, 1.0),
        DVec3::new(-1.0, 1.0, -1.0),
        DVec3::new(1.0, -1.0, -1.0),
    ]
    .into_iter()
    .enumerate()
    {
        let t2 = principal_axes(&pts, signs);
        out.push(Normalization {
            name: format!(
                "gsplat normalize_world_space (cameras, then the sparse points' principal axes, axis signs {})",
                ["+x +y +z", "-x -y +z", "-x +y -z", "+x -y -z"][k]
            ),
            to_model: t2 * t1,
        });
    }
    out
}

/// The rotation that turns `a` into `b` (nerfstudio's `rotation_matrix_between`).
fn rotation_between(a: DVec3, b: DVec3) -> DMat3 {
    let (a, b) = (a.normalize(), b.normalize());
    let mut v = a.cross(b);
    let eps = 1e-6;
    if v.abs().element_sum() < eps {
        let x = if a.x.abs() < eps { DVec3::X } else { DVec3::Y };
        v = a.cross(x);
    }
    let v = v.normalize();
    let k = skew(v);
    let theta = a.dot(b).clamp(-1.0, 1.0).acos();
    DMat3::IDENTITY + k * theta.sin() + (k * k) * (1.0 - theta.cos())
}

/// The normalization of nerfstudio's COLMAP dataparser with its defaults.
pub fn nerfstudio_normalization(m: &ColmapModel) -> Option<Normalization> {
    if m.images.is_empty() {
        return None;
    }
    // applied_transform: rows x, z, -y (COLMAP's -y, gravity's guess, becomes +z).
    let applied = DMat4::from_cols(
        glam::DVec4::new(1.0, 0.0, 0.0, 0.0),
        glam::DVec4::new(0.0, 0.0, -1.0, 0.0),
        glam::DVec4::new(0.0, 1.0, 0.0, 0.0),
        glam::DVec4::W,
    );
    let opengl = DMat4::from_diagonal(glam::DVec4::new(1.0, -1.0, -1.0, 1.0));
    // nerfstudio holds the poses in float32.
    let poses: Vec<DMat4> = m
        .images
        .iter()
        .map(|i| {
            let p = applied * i.camera_to_world() * opengl;
            DMat4::from_cols_array(&p.to_cols_array().map(|x| x as f32 as f64))
        })
        .collect();
    let n = poses.len() as f64;
    let mean_origin = poses
        .iter()
        .fold(DVec3::ZERO, |a, p| a + p.w_axis.truncate())
        / n;
    let up = poses
        .iter()
        .fold(DVec3::ZERO, |a, p| a + p.y_axis.truncate())
        / n;
    let rotation = rotation_between(up.normalize(), DVec3::Z);
    let transform = rt(rotation, rotation * -mean_origin);
    let max = poses
        .iter()
        .map(|p| {
            transform
                .transform_point3(p.w_axis.truncate())
                .abs()
                .max_element()
        })
        .fold(0.0, f64::max);
    if max.is_nan() || max <= 0.0 {
        return None;
    }
    Some(Normalization {
        name: "nerfstudio colmap dataparser (orientation up, centre poses, auto scale)".into(),
        to_model: DMat4::from_scale(DVec3::splat(1.0 / max)) * transform * applied,
    })
}

/// Every candidate for `m`: gsplat's, then nerfstudio's.
pub fn normalizations(m: &ColmapModel) -> Vec<Normalization> {
    let mut v = gsplat_normalizations(m);
    v.extend(nerfstudio_normalization(m));
    v.retain(|n| n.to_model.is_finite() && n.to_model.determinant().abs() > 1e-300);
    v
}

/// One candidate's frame check.
#[derive(Clone, Debug)]
pub struct Tried {
    pub name: String,
    /// Maps the Gaussians into the lines' frame.
    pub matrix: DMat4,
    pub check: FrameCheck,
    /// Median RMS distance of the Gaussians within r of a segment (lines' units); NaN
    /// when no segment has any.
    pub residual: f64,
}

/// What the search found: every candidate's check, and the one taken.
#[derive(Clone, Debug)]
pub struct FrameSearch {
    pub tried: Vec<Tried>,
    /// Index into `tried` of the frame taken.
    pub found: Option<usize>,
}

impl FrameSearch {
    pub fn best(&self) -> Option<&Tried> {
        self.found.map(|k| &self.tried[k])
    }

    /// One line per candidate: its name, segments near, verdict.
    pub fn summary(&self) -> String {
        self.tried
            .iter()
            .map(|t| {
                format!(
                    "{}: {} of {} segments near Gaussians ({:?})",
                    t.name,
                    t.check.near,
                    t.check.segments,
                    t.check.verdict()
                )
            })
            .collect::<Vec<_>>()
            .join("; ")
    }
}

/// The frame check of `segments` against `centers` mapped by `matrix`, at `radius`.
pub fn try_matrix(
    name: &str,
    matrix: DMat4,
    centers: &[[f32; 3]],
    segments: &[Segment],
    radius: f64,
) -> Result<Tried, EngineError> {
    let mapped: Vec<[f32; 3]> = centers
        .iter()
        .map(|c| {
            let p = matrix.transform_point3(DVec3::new(c[0] as f64, c[1] as f64, c[2] as f64));
            [p.x as f32, p.y as f32, p.z as f32]
        })
        .collect();
    let ws = WorkingSet::new(&mapped, segments);
    let grid = Arc::new(Grid::build(&ws.points, ws.bounds, radius));
    let engine = CpuEngine::new(grid);
    let check = check_frames(&engine, segments, radius, &mapped)?;
    let queries: Vec<Query> = segments.iter().map(|s| Query::new(*s, radius)).collect();
    let stats = engine.stats(&queries, Want::SUMS)?;
    let rms: Vec<f64> = stats
        .iter()
        .filter(|s| s.count > 0)
        .map(|s| (s.sum_d2 / s.count as f64).sqrt())
        .collect();
    Ok(Tried {
        name: name.to_string(),
        matrix,
        check,
        residual: median(rms),
    })
}

/// The candidate with the most segments near Gaussians among those whose verdict is
/// [`FrameVerdict::Same`] and, when `baseline_near` is given (the segments near Gaussians
/// without any map), with more than it; the first of equals.
pub fn pick(tried: &[Tried], baseline_near: Option<usize>) -> Option<usize> {
    tried
        .iter()
        .enumerate()
        .filter(|(_, t)| t.check.verdict() == FrameVerdict::Same)
        .filter(|(_, t)| baseline_near.is_none_or(|b| t.check.near > b))
        .max_by_key(|(k, t)| (t.check.near, std::cmp::Reverse(*k)))
        .map(|(k, _)| k)
}

/// Tries every normalization of `model` (see the module) on `centers` (the model's frame)
/// and `segments` (the COLMAP frame) at `radius`, and [`pick`]s one.
pub fn search(
    model: &ColmapModel,
    centers: &[[f32; 3]],
    segments: &[Segment],
    radius: f64,
    baseline_near: Option<usize>,
) -> Result<FrameSearch, EngineError> {
    let mut tried = Vec::new();
    for n in normalizations(model) {
        tried.push(try_matrix(
            &n.name,
            n.to_colmap(),
            centers,
            segments,
            radius,
        )?);
    }
    let found = pick(&tried, baseline_near);
    Ok(FrameSearch { tried, found })
}

/// The matrix as 4 rows of text (full precision), for messages and files.
pub fn matrix_rows(m: &DMat4) -> String {
    (0..4)
        .map(|r| {
            let row = m.row(r);
            format!("{:?} {:?} {:?} {:?}", row.x, row.y, row.z, row.w)
        })
        .collect::<Vec<_>>()
        .join("\n")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jacobi_finds_the_eigenvectors_of_a_turned_diagonal() {
        let r = DMat3::from_quat(glam::DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -1.1, 0.7));
        let m = r * DMat3::from_diagonal(DVec3::new(5.0, 2.0, 0.5)) * r.transpose();
        let (vals, vecs) = symmetric_eigen(m);
        for k in 0..3 {
            let v = vecs.col(k);
            assert!((m * v - v * vals[k]).length() < 1e-12, "{k}: {vals}");
            assert!((v.length() - 1.0).abs() < 1e-12);
        }
        let mut s = vals.to_array();
        s.sort_by(f64::total_cmp);
        assert!(
            (s[0] - 0.5).abs() < 1e-12 && (s[2] - 5.0).abs() < 1e-12,
            "{vals}"
        );
    }

    #[test]
    fn the_rotation_between_two_directions_turns_one_onto_the_other() {
        for a in [
            DVec3::new(0.2, -0.9, 0.3),
            DVec3::Z,
            -DVec3::Z,
            DVec3::new(0.0, 0.0, -2.0),
        ] {
            let r = rotation_between(a, DVec3::Z);
            assert!((r * a.normalize() - DVec3::Z).length() < 1e-9, "{a}");
            assert!((r.determinant() - 1.0).abs() < 1e-9);
        }
    }

    #[test]
    fn cameras_looking_at_a_point_are_centred_on_it_at_unit_distance() {
        // Cameras at distance 4 around the origin, looking at it, image y down along -z
        // (world z up): the similarity keeps the focus at the origin and scales by 1/4.
        let focus = DVec3::ZERO;
        let c2w: Vec<DMat4> = (0..8)
            .map(|k| {
                let a = k as f64 * std::f64::consts::TAU / 8.0;
                let c = focus + DVec3::new(a.cos(), a.sin(), 0.5).normalize() * 4.0;
                let fwd = (focus - c).normalize();
                let right = fwd.cross(DVec3::Z).normalize();
                let down = fwd.cross(right);
                rt(DMat3::from_cols(right, down, fwd), c)
            })
            .collect();
        let t = similarity_from_cameras(&c2w);
        assert!(t.transform_point3(focus).length() < 1e-9);
        for m in &c2w {
            let c = t.transform_point3(m.w_axis.truncate());
            assert!((c.length() - 1.0).abs() < 1e-9, "{c}");
        }
        // The cameras' mean up (world +z) becomes -y, camera space's up, as gsplat's
        // code does (its comment says z+).
        let up = t.transform_vector3(DVec3::Z);
        assert!(up.normalize().dot(-DVec3::Y) > 1.0 - 1e-9, "{up}");
    }
}
