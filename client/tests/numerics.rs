//! Numerical stability of importance, the quality controller and visibility
//! (horizon-fitted near/far, horizon culling) on extreme cases, against brute
//! force references (docs/NUMERICS.md).
//!
//! `cargo test -p planet-client --test numerics -- --nocapture` prints the
//! measured worst cases (lines starting with `NUMERICS`).

use glam::DVec3;
use planet_client::importance::{block_distance, importance, screen_space_error};
use planet_client::quality::{QualityConfig, QualityController, QualityMode, QF_MAX, QF_MIN};
use planet_client::visibility::{
    near_far, segment_hits_ball, Basis, BlockBounds, Camera, View, NEAR_MIN,
};
use planet_core::cube::FaceCoord;
use planet_core::{BlockId, Datum, Face};

const R_EARTH: f64 = 6_371_000.0;

const QFS: [f64; 12] = [
    f64::NEG_INFINITY,
    -1.0,
    0.0,
    5e-324,
    1e-300,
    1e-6,
    1.0,
    1e4,
    1e10,
    1e300,
    f64::MAX,
    f64::INFINITY,
];

const DISTANCES: [f64; 14] = [
    f64::NEG_INFINITY,
    -1e300,
    -1.0,
    0.0,
    5e-324,
    1e-300,
    0.01,
    1.0,
    1e4,
    R_EARTH,
    1000.0 * R_EARTH,
    1e300,
    f64::MAX,
    f64::INFINITY,
];

#[test]
fn importance_is_finite_and_monotone_at_the_bounds() {
    let radii = [0.0, 5e-324, 1.0, 1e7, 1e300, f64::INFINITY, f64::NAN, -1.0];
    let widths = [0.0, 1.0, 64.0, 4096.0, f64::INFINITY, f64::NAN];
    let mut n = 0;
    for &r in &radii {
        for &w in &widths {
            // NaN quality factor and NaN distance: finite.
            assert!(importance(1.0, r, w, f64::NAN).is_finite());
            assert!(importance(f64::NAN, r, w, 1e4).is_finite());
            for &qf in &QFS {
                let mut last = f64::NEG_INFINITY;
                for &d in &DISTANCES {
                    let i = importance(d, r, w, qf);
                    assert!(
                        i.is_finite() && (-64.0..=64.0).contains(&i),
                        "{d} {r} {w} {qf}"
                    );
                    // Monotone: farther is never more important.
                    assert!(i >= last, "d {d} r {r} w {w} qf {qf}: {i} < {last}");
                    last = i;
                    n += 1;
                }
            }
            for &d in &DISTANCES {
                // Monotone in QF: a higher quality factor is never less important.
                let mut last = f64::INFINITY;
                for &qf in &QFS {
                    let i = importance(d, r, w, qf);
                    assert!(i <= last, "d {d} r {r} w {w} qf {qf}: {i} > {last}");
                    last = i;
                }
            }
        }
    }
    // Distances from eyes at the centre, on a block, 1000 Earth radii away.
    for eye in [
        DVec3::ZERO,
        DVec3::X * R_EARTH,
        DVec3::X * 1e3 * R_EARTH,
        DVec3::splat(1e300),
    ] {
        let d = block_distance(eye, DVec3::X * R_EARTH, 1e3);
        assert!(importance(d, 1e3, 64.0, 1e4).is_finite());
    }
    for &d in &DISTANCES {
        for fov in [
            0.0,
            1e-9,
            1f64.to_radians(),
            170f64.to_radians(),
            std::f64::consts::PI,
        ] {
            assert!(screen_space_error(3.0, d, 1080.0, fov).is_finite());
        }
    }
    println!("NUMERICS importance: {n} (distance, radius, width, QF) cases finite in [-64, 64] and monotone");
}

#[test]
fn quality_controller_stays_in_bounds_under_hostile_input() {
    let hostile = [
        0.0,
        -1.0,
        5e-324,
        1e-300,
        f64::NAN,
        f64::INFINITY,
        f64::NEG_INFINITY,
        1e300,
    ];
    for initial in [f64::NAN, 0.0, -1.0, 5e-324, f64::INFINITY, 1e300] {
        for mode in [
            QualityMode::Fixed,
            QualityMode::TargetFps(60.0),
            QualityMode::TargetFps(f64::NAN),
            QualityMode::TargetFps(1e-300),
            QualityMode::TriangleBudget(1e300),
            QualityMode::TriangleBudget(0.0),
        ] {
            for gain in [0.5, f64::NAN, f64::INFINITY, -1.0] {
                for (smoothing, ceiling) in [
                    (0.5, QF_MAX),
                    (f64::NAN, f64::NAN),
                    (2.0, 0.0),
                    (0.5, 1e4),
                    (0.5, f64::NEG_INFINITY),
                ] {
                    let mut c = QualityController::new(QualityConfig {
                        mode,
                        initial,
                        gain,
                        smoothing,
                        tolerance: f64::NAN,
                        max_step: f64::INFINITY,
                        ceiling,
                    });
                    for &s in &hostile {
                        for &t in &hostile {
                            // Intervals and costs alike.
                            for q in [c.update(s, t), c.update_with_cost(s, t)] {
                                assert!(q.is_finite() && (QF_MIN..=QF_MAX).contains(&q));
                                let i = importance(1e4, 1e3, 64.0, q);
                                assert!(i.is_finite());
                            }
                        }
                    }
                }
            }
        }
    }
}

fn unit(lat: f64, lon: f64) -> DVec3 {
    let (sa, ca) = lat.sin_cos();
    let (so, co) = lon.sin_cos();
    DVec3::new(ca * co, ca * so, sa)
}

/// Altitudes from the brief: 0, 1 cm, 1 m, 10 km, one and 1000 radii.
fn altitudes(r: f64) -> [f64; 6] {
    [0.0, 0.01, 1.0, 10_000.0, r, 1000.0 * r]
}

/// View directions at `eye`: straight down, straight up, along the horizon
/// (tangent), 1 mrad below/above it, and 45° down.
fn directions(eye: DVec3) -> Vec<DVec3> {
    let up = eye.normalize();
    let east = DVec3::Z.cross(up).try_normalize().unwrap_or(DVec3::X);
    vec![
        -up,
        up,
        east,
        (east - up * 1e-3).normalize(),
        (east + up * 1e-3).normalize(),
        (east - up).normalize(),
    ]
}

/// Surface points: a spherical Fibonacci lattice at both radii plus the
/// points near the eye's nadir (where the near plane matters).
fn surface_points(eye: DVec3, r_min: f64, r_max: f64) -> Vec<DVec3> {
    let mut pts = vec![];
    let n = 4000;
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    for k in 0..n {
        let z = 1.0 - 2.0 * (k as f64 + 0.5) / n as f64;
        let rho = (1.0 - z * z).sqrt();
        let d = DVec3::new(
            rho * (golden * k as f64).cos(),
            rho * (golden * k as f64).sin(),
            z,
        );
        pts.push(d * r_min);
        pts.push(d * r_max);
    }
    let up = eye.try_normalize().unwrap_or(DVec3::Z);
    let east = DVec3::Z.cross(up).try_normalize().unwrap_or(DVec3::X);
    let north = up.cross(east);
    for k in 0..=40 {
        // Ring of points at geometric distances from the nadir.
        let ang = 1e-9 * 1.6f64.powi(k);
        for m in 0..8 {
            let az = m as f64 * std::f64::consts::FRAC_PI_4;
            let d = (up * ang.cos() + (east * az.cos() + north * az.sin()) * ang.sin()).normalize();
            pts.push(d * r_min);
            pts.push(d * r_max);
        }
    }
    pts
}

/// Brute force for the horizon-fitted planes: every surface point that is
/// in the view frustum (side planes), not hidden by the min sphere and at
/// least `near_floor` away lies between the near and far planes.
#[test]
fn near_far_never_cull_a_visible_surface_point() {
    let mut cases = 0;
    let mut worst_far_slack = f64::INFINITY; // min over cases of (far − deepest visible depth)/far
    let mut worst_near_slack = f64::INFINITY; // min of (shallowest visible depth − near)
    let mut worst_far_ratio = 0.0f64; // max of far / deepest visible depth (tightness)
    for radius in [1_000.0, R_EARTH, 70_000_000.0] {
        let relief = (radius * 1e-3).min(10_000.0);
        let (r_min, r_max) = (radius - relief, radius + relief);
        for alt in altitudes(radius) {
            for (ea, eb) in [
                (0.3, 0.2),
                (std::f64::consts::FRAC_PI_2, 0.0),
                (0.0, std::f64::consts::PI),
            ] {
                let eye = unit(ea, eb) * (r_max + alt);
                let pts = surface_points(eye, r_min, r_max);
                for dir in directions(eye) {
                    for fov_deg in [1.0f64, 60.0, 170.0] {
                        let mut cam = Camera::look_at(eye, eye + dir, unit(ea + 1.0, eb));
                        cam.fov_y = fov_deg.to_radians();
                        let (near, far) = near_far(&cam, r_min, r_max);
                        assert!(
                            near.is_finite() && far.is_finite() && near >= NEAR_MIN && far > near,
                            "{near} {far}"
                        );
                        let Basis {
                            forward: f,
                            right: r,
                            up: u,
                        } = cam.basis();
                        let ty = (cam.fov_y * 0.5).tan();
                        let tx = ty * cam.aspect;
                        let mut deepest = 0.0f64;
                        for p in &pts {
                            let q = *p - eye;
                            let z = q.dot(f);
                            if z <= 0.0 || q.dot(r).abs() > z * tx || q.dot(u).abs() > z * ty {
                                continue;
                            }
                            if segment_hits_ball(eye, *p, r_min) {
                                continue;
                            }
                            deepest = deepest.max(z);
                            assert!(z <= far, "radius {radius} alt {alt} dir {dir} fov {fov_deg}: depth {z} > far {far}");
                            worst_far_slack = worst_far_slack.min((far - z) / far);
                            // Points closer than the clamped minimum cannot be kept.
                            if near > NEAR_MIN {
                                assert!(z >= near, "radius {radius} alt {alt} fov {fov_deg}: depth {z} < near {near}");
                                worst_near_slack = worst_near_slack.min(z - near);
                            }
                        }
                        if deepest > 1e3 {
                            worst_far_ratio = worst_far_ratio.max(far / deepest);
                        }
                        cases += 1;
                    }
                }
            }
        }
    }
    println!(
        "NUMERICS client near_far: {cases} cameras; smallest relative far margin {worst_far_slack:.3e}; smallest near margin {worst_near_slack:.3e} m; loosest far/deepest-visible-depth (when > 1 km) {worst_far_ratio:.3}"
    );
}

#[test]
fn camera_inside_the_planet_and_degenerate_cameras() {
    for radius in [1_000.0, R_EARTH, 70_000_000.0] {
        let (r_min, r_max) = (radius * 0.999, radius * 1.001);
        for eye in [
            DVec3::ZERO,
            DVec3::X * 1e-300,
            DVec3::Z * radius * 0.5,
            DVec3::Y * r_min,
            DVec3::Y * r_min.next_up(),
            DVec3::Y * r_min.next_down(),
            DVec3::splat(f64::NAN),
            DVec3::X * f64::INFINITY,
        ] {
            for fwd in [DVec3::X, -DVec3::Y, DVec3::ZERO, DVec3::splat(f64::NAN)] {
                for fov in [
                    1e-9,
                    1f64.to_radians(),
                    170f64.to_radians(),
                    std::f64::consts::PI,
                ] {
                    let mut cam = Camera::look_at(eye, eye + fwd, DVec3::Z);
                    cam.fov_y = fov;
                    let (near, far) = near_far(&cam, r_min, r_max);
                    assert!(
                        near.is_finite() && far.is_finite() && near > 0.0 && far > near,
                        "{eye} {fwd} {fov}: {near} {far}"
                    );
                }
            }
        }
    }
}

/// Horizon occlusion per point against a brute-force segment/ball test, for
/// eyes just above the min sphere (1e-9 m .. 1000 radii).
#[test]
fn horizon_test_never_hides_a_visible_point() {
    let mut hidden = 0;
    for radius in [1_000.0, R_EARTH, 70_000_000.0] {
        let r_min = radius - (radius * 1e-3).min(10_000.0);
        for alt in [1e-9, 0.01, 1.0, 10_000.0, radius, 1000.0 * radius] {
            let eye = unit(0.4, -2.0) * (r_min + alt);
            let cam = Camera::look_at(eye, DVec3::ZERO, DVec3::Z);
            let view = View::new(&cam, r_min, radius + 10.0);
            for p in surface_points(eye, r_min, r_min + 2.0 * (radius - r_min)) {
                if view.point_behind_horizon(p) {
                    hidden += 1;
                    assert!(
                        segment_hits_ball(eye, p, r_min),
                        "alt {alt}: {p} hidden but visible"
                    );
                }
            }
        }
    }
    println!("NUMERICS horizon occlusion: {hidden} points hidden, all confirmed by the segment/ball test");
}

/// Blocks: any level-4 block with a surface sample visible from the camera
/// (in the frustum, between near and far, not behind the min sphere) must
/// be reported visible, also when the camera is inside its bounds.
#[test]
fn visible_blocks_are_never_culled() {
    let datum = Datum::WGS84;
    let (h_min, h_max) = (-500.0, 3000.0);
    let r_min = datum.polar_radius() + h_min;
    let r_max = datum.equatorial_radius() + h_max;
    let level = 4u8;
    let mut checked = 0;
    let mut visible_blocks = 0;
    // Eyes: inside a block's bounding volume (on the surface at 1 cm, 1 m),
    // 10 km up, one radius, and on a cube corner.
    let corner = FaceCoord {
        face: Face::new(0).unwrap(),
        s: 1.0,
        t: 1.0,
    }
    .direction();
    let eyes = [
        (
            DVec3::from_array(
                FaceCoord {
                    face: Face::new(2).unwrap(),
                    s: 0.53,
                    t: 0.47,
                }
                .direction(),
            ),
            0.01,
        ),
        (DVec3::from_array(corner), 1.0),
        (unit(1.2, 3.0), 10_000.0),
        (unit(-0.2, -3.1), R_EARTH),
    ];
    let mut blocks = vec![];
    for f in Face::ALL {
        let n = 1u32 << level;
        for y in 0..n {
            for x in 0..n {
                let id = BlockId::new(f, level, x, y).unwrap();
                blocks.push((id, BlockBounds::single(&datum, id, h_min, h_max)));
            }
        }
    }
    for (dirn, alt) in eyes {
        let eye = DVec3::from_array(datum.position(dirn.to_array(), alt));
        for dir in directions(eye) {
            for fov_deg in [1.0f64, 60.0, 170.0] {
                let mut cam = Camera::look_at(eye, eye + dir, DVec3::Z);
                cam.fov_y = fov_deg.to_radians();
                let view = View::new(&cam, r_min, r_max);
                let Basis {
                    forward: f,
                    right: r,
                    up: u,
                } = cam.basis();
                let ty = (cam.fov_y * 0.5).tan();
                let tx = ty * cam.aspect;
                for (id, b) in &blocks {
                    let vis = view.is_visible(b);
                    let (s0, t0, s1, t1) = id.extent();
                    let k = 6;
                    let mut seen = false;
                    'outer: for j in 0..=k {
                        for i in 0..=k {
                            let fc = FaceCoord {
                                face: id.face,
                                s: s0 + (s1 - s0) * i as f64 / k as f64,
                                t: t0 + (t1 - t0) * j as f64 / k as f64,
                            };
                            for h in [h_min, 0.0, h_max] {
                                let p = DVec3::from_array(datum.position(fc.direction(), h));
                                let q = p - eye;
                                let z = q.dot(f);
                                if z < view.near
                                    || z > view.far
                                    || q.dot(r).abs() > z * tx
                                    || q.dot(u).abs() > z * ty
                                {
                                    continue;
                                }
                                if segment_hits_ball(eye, p, r_min) {
                                    continue;
                                }
                                seen = true;
                                break 'outer;
                            }
                        }
                    }
                    if seen {
                        visible_blocks += 1;
                        assert!(vis, "{id:?} has a visible sample but was culled (eye alt {alt}, dir {dir}, fov {fov_deg})");
                    }
                    checked += 1;
                }
            }
        }
    }
    println!("NUMERICS block visibility: {checked} (camera, block) pairs, {visible_blocks} with a visible sample, none culled");
}
