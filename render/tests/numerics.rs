//! Numerical stability of the renderer's CPU-side arithmetic (no GPU): f32
//! block-relative vertices, the camera-relative f32 model-view-projection,
//! reversed-Z f32 depth and the horizon-fitted clip planes, each against an
//! f64 reference (docs/NUMERICS.md).
//!
//! The vertex path is reproduced exactly as the renderer runs it:
//! `BlockMesh` stores `(p − centre) as f32`; `Renderer::encode` uploads
//! `(centre − eye) as f32` per block and `proj·view` composed in f64 then
//! cast to f32; the shader computes `clip = view_proj · (pos + offset)` in
//! f32.
//!
//! `CARGO_TARGET_DIR=/work/target-view cargo test -p planet-render --test numerics -- --nocapture`
//! prints the measured worst cases (lines starting with `NUMERICS`).

use planet_core::cube::FaceCoord;
use planet_core::horizon::{ClipPlanes, MIN_NEAR};
use planet_core::{BlockId, Datum, Face};
use planet_render::camera_relative::{camera_relative, low_part_f32, SplitOffset};
use planet_render::mesh::{sample_position, BlockMesh};
use planet_render::render::Basis;
use planet_render::{Camera, Projection};

const W: usize = 64;

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}
fn scale(a: [f64; 3], k: f64) -> [f64; 3] {
    [a[0] * k, a[1] * k, a[2] * k]
}
fn add(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

/// The core's horizon planes on this file's `[f64; 3]` vectors.
fn horizon_planes(eye: [f64; 3], dir: [f64; 3], r_min: f64, r_max: f64, hd: f64) -> ClipPlanes {
    planet_core::horizon::horizon_planes(eye.into(), dir.into(), r_min, r_max, hd)
}

/// A 16:9 camera (the renderer takes the aspect ratio from its target).
fn camera(eye: [f64; 3], forward: [f64; 3], up: [f64; 3], fov_y: f64) -> Camera {
    Camera {
        eye: eye.into(),
        forward: forward.into(),
        up: up.into(),
        fov_y,
        aspect: 16.0 / 9.0,
        viewport_height_px: 1080.0,
    }
}

/// `(right, up, forward)` of a camera as arrays.
fn basis(camera: &Camera) -> [[f64; 3]; 3] {
    let Basis { right, up, forward } = camera.basis();
    [right.to_array(), up.to_array(), forward.to_array()]
}

/// Column-major product, as `render/frame.rs` composes `proj · view`.
fn mat_mul(a: [[f64; 4]; 4], b: [[f64; 4]; 4]) -> [[f64; 4]; 4] {
    let mut out = [[0.0; 4]; 4];
    for col in 0..4 {
        for row in 0..4 {
            out[col][row] = (0..4).map(|k| a[k][row] * b[col][k]).sum();
        }
    }
    out
}

/// The f64 view-projection exactly as `Renderer::encode` builds it.
fn view_proj(camera: &Camera, proj: &Projection) -> [[f64; 4]; 4] {
    let [r, u, f] = basis(camera);
    let view = [
        [r[0], u[0], -f[0], 0.0],
        [r[1], u[1], -f[1], 0.0],
        [r[2], u[2], -f[2], 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    mat_mul(proj.matrix(), view)
}

/// `m · (p, 1)` in f32 with the shader's order of operations (column-major
/// matrix times vector: a sum of scaled columns, then rounding per step).
fn mul_f32(m: &[[f32; 4]; 4], p: [f32; 3]) -> [f32; 4] {
    let mut out = [0.0f32; 4];
    for row in 0..4 {
        out[row] = m[0][row] * p[0] + m[1][row] * p[1] + m[2][row] * p[2] + m[3][row];
    }
    out
}

fn mul_f64(m: &[[f64; 4]; 4], p: [f64; 3]) -> [f64; 4] {
    let mut out = [0.0f64; 4];
    for row in 0..4 {
        out[row] = m[0][row] * p[0] + m[1][row] * p[1] + m[2][row] * p[2] + m[3][row];
    }
    out
}

/// The block of `level` containing face coordinates `(s, t)`.
fn block_at(face: Face, level: u8, s: f64, t: f64) -> BlockId {
    let n = 1u32 << level;
    let x = ((s * n as f64) as u32).min(n - 1);
    let y = ((t * n as f64) as u32).min(n - 1);
    BlockId::new(face, level, x, y).unwrap()
}

/// A deterministic elevation grid: ±3000 m relief (1 m per unit).
fn grid(seed: u64) -> Vec<i16> {
    (0..(W + 1) * (W + 1))
        .map(|k| {
            let x = (k as u64 ^ seed).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 52;
            (x as i64 - 2048) as i16
        })
        .collect()
}

/// Camera sites: a face centre, the north pole, a cube corner, a cube edge
/// and a point on the antimeridian.
fn sites() -> Vec<(&'static str, Face, f64, f64)> {
    vec![
        ("face centre", Face::new(2).unwrap(), 0.5 + 1e-7, 0.5 + 1e-7),
        ("north pole", Face::new(0).unwrap(), 0.5, 0.5),
        ("cube corner", Face::new(0).unwrap(), 1.0, 1.0),
        ("cube edge", Face::new(1).unwrap(), 0.0, 0.3),
        ("antimeridian", Face::new(5).unwrap(), 0.5, 0.5),
    ]
}

/// Rendered camera-relative vertex positions against `f64 position − eye`,
/// for the block (at every level 0..=24) under cameras at 0, 1 cm, 1 m and
/// 10 km, on the Earth and on spheres of 1 km and 70 000 km.
#[test]
fn camera_relative_f32_vertices_within_10_km() {
    let datums = [
        ("WGS84", Datum::WGS84),
        ("sphere 1 km", Datum::Sphere { radius: 1_000.0 }),
        ("sphere 70000 km", Datum::Sphere { radius: 7.0e7 }),
    ];
    let mut worst_small = (0.0f64, String::new()); // blocks with radius ≤ 10 km
    let mut worst_any = (0.0f64, String::new());
    let mut worst_px = (0.0f64, String::new());
    let mut worst_5km = 0.0f64;
    let mut per_level = [0.0f64; 25];
    let mut radius_at_level = [0.0f64; 25];
    for (dname, datum) in datums {
        for (sname, face, s, t) in sites() {
            let ground = FaceCoord { face, s, t }.direction();
            for level in 0..=24u8 {
                let id = block_at(face, level, s, t);
                let g = grid(level as u64);
                let mesh = BlockMesh::build(&datum, id, W, &g, 1.0, 0.0);
                let r_block = mesh.radius;
                for alt in [0.0, 0.01, 1.0, 10_000.0] {
                    // Eye above the datum point of the camera site.
                    let eye = datum.position(ground, alt);
                    let down = scale(ground, -1.0);
                    let horizon = {
                        let e = [-ground[1], ground[0], 0.0];
                        let l = norm(e);
                        if l > 0.0 {
                            scale(e, 1.0 / l)
                        } else {
                            [1.0, 0.0, 0.0]
                        }
                    };
                    for (fwd, fov_deg) in [(down, 60.0f64), (horizon, 1.0), (horizon, 170.0)] {
                        let cam = camera(eye, fwd, ground, fov_deg.to_radians());
                        let aspect = 16.0 / 9.0;
                        let p = horizon_planes(eye, fwd, 1.0, 2.0, cam.half_diagonal_fov());
                        let proj = Projection {
                            near: MIN_NEAR.min(p.near),
                            far: p.far.max(1e5),
                            fov_y: cam.fov_y,
                            aspect,
                        };
                        let vp64 = view_proj(&cam, &proj);
                        let vp32 = vp64.map(|c| c.map(|v| v as f32));
                        // As Renderer::encode: centre − eye in f64, split in
                        // two f32 parts.
                        let rel_c = sub(mesh.centre, eye);
                        let off = SplitOffset::new(rel_c);
                        for (k, v) in mesh.vertices.iter().enumerate() {
                            let (i, j) = (k % (W + 1), k / (W + 1));
                            let h = g[k] as f64;
                            let reference = sub(sample_position(&datum, id, W, i, j, h), eye);
                            let dist = norm(reference);
                            if dist > 10_000.0 {
                                continue;
                            }
                            // The shader's camera_relative() in f32.
                            let lo = low_part_f32(v.pos_lo);
                            let rel32 = camera_relative(v.pos, lo, off.hi, off.lo);
                            assert!(rel32.iter().all(|c| c.is_finite()));
                            let e = norm(sub(rel32.map(|c| c as f64), reference));
                            // Forward bound: one rounding of the result (half
                            // an ulp per coordinate), the f16 residual's own
                            // rounding (2⁻¹¹ of it) and the f64 roundings of
                            // positions up to 7·10⁷ m (≤ 0.1 µm).
                            let lo_norm = norm(lo.map(|c| c as f64));
                            let bound =
                                2f64.powi(-24) * dist * 1.01 + 2f64.powi(-11) * lo_norm + 1e-7;
                            assert!(e <= bound, "{dname} {sname} L{level}: {e} > {bound}");
                            let tag = format!("{dname}, {sname}, level {level} (block radius {r_block:.0} m), alt {alt} m, {dist:.0} m from the eye");
                            if e > worst_any.0 {
                                worst_any = (e, tag.clone());
                            }
                            per_level[level as usize] = per_level[level as usize].max(e);
                            if dname == "WGS84" {
                                radius_at_level[level as usize] =
                                    radius_at_level[level as usize].max(r_block);
                            }
                            if r_block <= 10_000.0 {
                                if e > worst_small.0 {
                                    worst_small = (e, tag.clone());
                                }
                                if dist <= 5_000.0 {
                                    worst_5km = worst_5km.max(e);
                                }
                            }
                            // The bound, for every block size.
                            assert!(e < 1e-3, "{tag}: error {e} m");
                            // Projected: pixel error on a 1080-px-high target.
                            let c32 = mul_f32(&vp32, rel32);
                            let c64 = mul_f64(&vp64, reference);
                            if c64[3] > proj.near {
                                let px = 540.0
                                    * ((c32[0] as f64 / c32[3] as f64 - c64[0] / c64[3]).powi(2)
                                        + (c32[1] as f64 / c32[3] as f64 - c64[1] / c64[3])
                                            .powi(2))
                                    .sqrt();
                                let inside = (c64[0] / c64[3]).abs() <= 1.0
                                    && (c64[1] / c64[3]).abs() <= 1.0;
                                if inside && r_block <= 10_000.0 && px > worst_px.0 {
                                    worst_px = (px, format!("{tag}, fov {fov_deg}°"));
                                }
                            }
                        }
                    }
                }
            }
        }
    }
    println!("NUMERICS f32 camera-relative vertex within 10 km, blocks of radius <= 10 km: worst {:.3e} m at {}", worst_small.0, worst_small.1);
    println!("NUMERICS f32 camera-relative vertex within 5 km, blocks of radius <= 10 km: worst {worst_5km:.3e} m");
    println!(
        "NUMERICS f32 camera-relative vertex within 10 km, any block: worst {:.3e} m at {}",
        worst_any.0, worst_any.1
    );
    for l in 0..=24 {
        println!("NUMERICS   level {l:2}: WGS84 block radius {:>10.1} m, worst vertex error (all datums) {:.3e} m", radius_at_level[l], per_level[l]);
    }
    println!("NUMERICS f32 model-view-projection, on-screen vertices within 10 km of small blocks: worst {:.3e} px (1080 px high) at {}", worst_px.0, worst_px.1);
    assert!(worst_px.0 < 0.05, "{}", worst_px.0);
}

/// Reversed-Z Depth32Float: the distance error of the f32 pipeline (matrix
/// and division in f32, decoded with `Projection::view_depth`) and the
/// distance step implied by one ulp of the depth value.
#[test]
fn reversed_z_depth_resolution() {
    let datum = Datum::WGS84;
    let (r_min, r_max) = (
        datum.polar_radius() - 11_000.0,
        datum.equatorial_radius() + 8_848.0,
    );
    let ground = FaceCoord {
        face: Face::new(2).unwrap(),
        s: 0.5,
        t: 0.5,
    }
    .direction();
    let east = [0.0, 1.0, 0.0];
    let mut worst = 0.0f64;
    let mut worst_ulp = 0.0f64;
    // (altitude, distances looked at); "horizon" is the geometric horizon
    // distance sqrt(2Rh + h²) from 10 km.
    let r = datum.equatorial_radius();
    let hz = (2.0 * r * 10_000.0 + 1e8).sqrt();
    for (alt, dists) in [
        (1.0, vec![1.0, 10_000.0]),
        (10_000.0, vec![10_000.0, hz]),
        (1.0, vec![MIN_NEAR * 2.0, 1.0]),
    ] {
        let eye = datum.position(ground, alt);
        for fov_deg in [1.0f64, 60.0, 170.0] {
            let cam = camera(eye, east, ground, fov_deg.to_radians());
            let aspect = 16.0 / 9.0;
            let p = horizon_planes(eye, east, r_min, r_max, cam.half_diagonal_fov());
            for far in [p.far, f64::INFINITY] {
                let proj = Projection {
                    near: p.near,
                    far,
                    fov_y: cam.fov_y,
                    aspect,
                };
                let vp32 = view_proj(&cam, &proj).map(|c| c.map(|v| v as f32));
                let (a, b) = if far.is_finite() {
                    let a = p.near / (far - p.near);
                    (a, a * far)
                } else {
                    (0.0, p.near)
                };
                for &d in &dists {
                    if d < p.near || d > far {
                        continue;
                    }
                    let rel = scale(east, d).map(|v| v as f32);
                    let c = mul_f32(&vp32, rel);
                    let depth = c[2] / c[3];
                    assert!(depth.is_finite() && depth > 0.0 && depth <= 1.0, "{depth}");
                    let back = proj.view_depth(depth).unwrap();
                    let e = (back - d).abs() / d;
                    // One ulp of depth: d(depth)/d(dist) = −B/dist².
                    let ulp = (depth.next_up() - depth) as f64;
                    let step = ulp * d * d / b / d;
                    let _ = a;
                    println!(
                        "NUMERICS depth: alt {alt} m, fov {fov_deg}°, near {:.3} m, far {}, distance {d:.1} m: depth {depth:.3e}, decoded relative error {e:.2e}, one-ulp step {:.3e} m ({step:.2e} relative)",
                        p.near,
                        if far.is_finite() { format!("{far:.0} m") } else { "inf".into() },
                        step * d
                    );
                    worst = worst.max(e);
                    worst_ulp = worst_ulp.max(step);
                    assert!(e < 1e-3 && step < 1e-3, "{e} {step}");
                }
            }
        }
    }
    println!("NUMERICS depth: worst decoded relative distance error {worst:.3e}, worst one-ulp relative step {worst_ulp:.3e}");
}

/// The renderer's horizon planes against brute force: every surface point
/// in the frustum that the min sphere does not hide lies between near and
/// far (points closer than the clamped minimum near excepted), and the
/// planes are finite with `0 < near < far`.
#[test]
fn horizon_planes_never_cull_a_visible_surface_point() {
    let mut cases = 0;
    let mut min_far_margin = f64::INFINITY;
    let mut min_near_margin = f64::INFINITY;
    for radius in [1_000.0f64, 6_371_000.0, 70_000_000.0] {
        let relief = (radius * 1e-3).min(10_000.0);
        let (r_min, r_max) = (radius - relief, radius + relief);
        // Surface points (Fibonacci lattice) on both spheres.
        let n = 3000;
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        let mut pts = vec![];
        for k in 0..n {
            let z = 1.0 - 2.0 * (k as f64 + 0.5) / n as f64;
            let rho = (1.0 - z * z).sqrt();
            let d = [
                rho * (golden * k as f64).cos(),
                rho * (golden * k as f64).sin(),
                z,
            ];
            pts.push(scale(d, r_min));
            pts.push(scale(d, r_max));
        }
        for alt in [0.0, 0.01, 1.0, 10_000.0, radius, 1000.0 * radius] {
            let up = FaceCoord {
                face: Face::new(4).unwrap(),
                s: 0.9,
                t: 0.2,
            }
            .direction();
            let eye = scale(up, r_max + alt);
            let e1 = {
                let e = [-up[1], up[0], 0.0];
                scale(e, 1.0 / norm(e))
            };
            let mut local = pts.clone();
            for k in 0..=40 {
                let ang = 1e-9 * 1.6f64.powi(k);
                let d = add(scale(up, ang.cos()), scale(e1, ang.sin()));
                local.push(scale(d, r_min));
                local.push(scale(d, r_max));
            }
            for fwd in [
                scale(up, -1.0),
                up,
                e1,
                add(e1, scale(up, -1e-3)),
                add(e1, scale(up, 1e-3)),
                add(e1, scale(up, -1.0)),
            ] {
                for fov_deg in [1.0f64, 60.0, 170.0] {
                    let cam = camera(eye, fwd, [0.0, 0.0, 1.0], fov_deg.to_radians());
                    let aspect = 16.0 / 9.0;
                    let p = horizon_planes(eye, fwd, r_min, r_max, cam.half_diagonal_fov());
                    assert!(
                        p.near.is_finite() && p.far.is_finite() && p.near > 0.0 && p.far > p.near,
                        "{p:?}"
                    );
                    let [r, u, f] = basis(&cam);
                    let ty = (cam.fov_y * 0.5).tan();
                    let tx = ty * aspect;
                    for q in &local {
                        let d = sub(*q, eye);
                        let z = dot(d, f);
                        if z <= 0.0 || dot(d, r).abs() > z * tx || dot(d, u).abs() > z * ty {
                            continue;
                        }
                        // Hidden by the min sphere (segment/ball)?
                        let dd = dot(d, d);
                        let t = (-dot(eye, d) / dd).clamp(0.0, 1.0);
                        if norm(add(eye, scale(d, t))) < r_min {
                            continue;
                        }
                        assert!(
                            z <= p.far,
                            "radius {radius} alt {alt} fov {fov_deg}: depth {z} > far {}",
                            p.far
                        );
                        min_far_margin = min_far_margin.min((p.far - z) / p.far);
                        if p.near > MIN_NEAR {
                            assert!(
                                z >= p.near,
                                "radius {radius} alt {alt} fov {fov_deg}: depth {z} < near {}",
                                p.near
                            );
                            min_near_margin = min_near_margin.min(z - p.near);
                        }
                    }
                    cases += 1;
                }
            }
        }
    }
    // Degenerate inputs.
    for eye in [
        [0.0; 3],
        [f64::NAN, 0.0, 0.0],
        [1e300, 0.0, 0.0],
        [f64::INFINITY, 0.0, 0.0],
        [6.3e6, 0.0, 0.0],
    ] {
        for dir in [
            [0.0; 3],
            [1.0, 0.0, 0.0],
            [f64::NAN, 1.0, 0.0],
            [-1.0, 1e-300, 0.0],
        ] {
            for hd in [0.0, 1e-9, 1.5, std::f64::consts::FRAC_PI_2, f64::NAN] {
                let p = horizon_planes(eye, dir, 6.37e6, 6.38e6, hd);
                assert!(
                    p.near.is_finite() && p.far.is_finite() && p.near > 0.0 && p.far > p.near,
                    "{eye:?} {dir:?} {hd}: {p:?}"
                );
            }
        }
    }
    println!("NUMERICS view horizon_planes: {cases} cameras; smallest relative far margin {min_far_margin:.3e}; smallest near margin {min_near_margin:.3e} m");
}

/// Elevations at the int16 limits and the SRTM void value −32768 (which a
/// hostile database could contain): every vertex attribute stays finite,
/// normals are unit, for realistic and for the most extreme scales the
/// format accepts.
#[test]
fn int16_limits_and_voids_give_finite_vertices() {
    let id_of =
        |level: u8| BlockId::new(Face::new(3).unwrap(), level, 0, (1u32 << level) - 1).unwrap();
    let grids: Vec<(&str, Vec<i16>)> = vec![
        ("all -32768", vec![i16::MIN; (W + 1) * (W + 1)]),
        ("all 32767", vec![i16::MAX; (W + 1) * (W + 1)]),
        (
            "alternating",
            (0..(W + 1) * (W + 1))
                .map(|k| if k % 3 == 0 { i16::MIN } else { i16::MAX })
                .collect(),
        ),
        ("one void", {
            let mut g = vec![100i16; (W + 1) * (W + 1)];
            g[(W / 2) * (W + 1) + W / 2] = i16::MIN;
            g
        }),
        ("all -1000", vec![-1000; (W + 1) * (W + 1)]),
    ];
    let mut n = 0;
    for datum in [
        Datum::WGS84,
        Datum::Sphere { radius: 1_000.0 },
        Datum::Sphere { radius: 7.0e7 },
    ] {
        for (name, g) in &grids {
            // Header scale/offset: 1 m, 0.1 m, and the extremes that
            // `format.rs` accepts (finite, positive scale; finite offset).
            for (sc, off) in [
                (1.0f32, 0.0f32),
                (0.1, 0.0),
                (f32::MAX, 0.0),
                (f32::MIN_POSITIVE, f32::MAX),
                (1.0, f32::MIN),
            ] {
                for level in [0u8, 12, 24] {
                    let m = BlockMesh::build(&datum, id_of(level), W, g, sc as f64, off as f64);
                    assert!(
                        m.centre.iter().all(|c| c.is_finite()) && m.radius.is_finite(),
                        "{name} {sc} {off}"
                    );
                    for v in &m.vertices {
                        let ok = v
                            .pos
                            .iter()
                            .chain(v.normal.iter())
                            .chain(v.uv.iter())
                            .all(|c| c.is_finite())
                            && v.alt.is_finite();
                        assert!(
                            ok,
                            "{datum:?} {name} scale {sc} offset {off} level {level}: {v:?}"
                        );
                        let nl = (v.normal.iter().map(|c| (*c as f64).powi(2)).sum::<f64>()).sqrt();
                        assert!((nl - 1.0).abs() < 1e-6, "{name}: normal length {nl}");
                        n += 1;
                    }
                }
            }
        }
    }
    println!("NUMERICS int16 limits / voids: {n} vertices finite with unit normals");
}
