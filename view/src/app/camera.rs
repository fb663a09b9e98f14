//! Camera geometry and the interactive fly / orbit controller.
//!
//! Positions are planet-centred f64 metres. Local frames use the geodetic
//! normal of the datum (`direction_from_lat_lon`), east and north.

use glam::DVec3;
use planet_client::tree::{PartialTree, Samples};
use planet_client::Camera;
use planet_core::cube::direction_from_lat_lon;
use planet_core::cube::FaceCoord;
use planet_core::format::Header;
use planet_core::{BlockId, Datum};

/// Vertical field of view of the viewer (radians).
pub const FOV_Y: f64 = 1.0;

/// Local (up, east, north) unit vectors at geodetic latitude / longitude
/// (degrees).
pub fn local_frame(lat_deg: f64, lon_deg: f64) -> (DVec3, DVec3, DVec3) {
    let up = DVec3::from(direction_from_lat_lon(
        lat_deg.to_radians(),
        lon_deg.to_radians(),
    ));
    let mut east = DVec3::Z.cross(up);
    if east.length_squared() < 1e-20 {
        east = DVec3::X;
    }
    let east = east.normalize();
    let north = up.cross(east);
    (up, east, north)
}

/// Planet-frame position of (lat, lon, alt) in degrees and metres.
pub fn geodetic_to_position(datum: &Datum, lat_deg: f64, lon_deg: f64, alt: f64) -> DVec3 {
    let n = direction_from_lat_lon(lat_deg.to_radians(), lon_deg.to_radians());
    DVec3::from(datum.position(n, alt))
}

/// Geodetic (lat°, lon°, alt m) of a planet-frame position (the standard
/// fixed-point iteration on the latitude).
pub fn position_to_geodetic(datum: &Datum, p: DVec3) -> (f64, f64, f64) {
    let a = datum.equatorial_radius();
    let e2 = datum.e2();
    let lon = p.y.atan2(p.x);
    let rho = (p.x * p.x + p.y * p.y).sqrt();
    let mut lat = p.z.atan2(rho * (1.0 - e2));
    let mut h = 0.0;
    for _ in 0..10 {
        let s = lat.sin();
        let n = a / (1.0 - e2 * s * s).sqrt();
        h = if lat.cos().abs() > 1e-9 {
            rho / lat.cos() - n
        } else {
            p.z.abs() - n * (1.0 - e2)
        };
        lat = p.z.atan2(rho * (1.0 - e2 * n / (n + h)));
    }
    (lat.to_degrees(), lon.to_degrees(), h)
}

/// Fly or orbit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Mode {
    /// Free flight: position and heading / pitch in the local frame.
    Fly,
    /// Orbit around a surface point at a range, heading and tilt.
    Orbit,
}

/// The interactive camera state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Controller {
    /// Current mode.
    pub mode: Mode,
    /// Fly: position.
    pub lat: f64,
    /// Fly: longitude (degrees).
    pub lon: f64,
    /// Fly: altitude above the datum (metres).
    pub alt: f64,
    /// Fly: heading (degrees from north, clockwise) of the view.
    pub heading: f64,
    /// Fly: pitch (degrees, negative looks down).
    pub pitch: f64,
    /// Orbit: target latitude (degrees).
    pub target_lat: f64,
    /// Orbit: target longitude (degrees).
    pub target_lon: f64,
    /// Orbit: target altitude above the datum (metres).
    pub target_alt: f64,
    /// Orbit: distance from the target (metres).
    pub range: f64,
    /// Orbit: azimuth of the camera seen from the target (degrees).
    pub azimuth: f64,
    /// Orbit: tilt from the vertical (degrees, 0 looks straight down).
    pub tilt: f64,
}

/// Held keys and mouse motion of one frame.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Input {
    /// Forward (+1) / back (−1).
    pub forward: f64,
    /// Right (+1) / left (−1).
    pub right: f64,
    /// Up (+1) / down (−1).
    pub up: f64,
    /// Mouse drag in pixels since the last frame.
    pub drag: (f64, f64),
    /// Scroll steps since the last frame (positive: closer / lower).
    pub scroll: f64,
    /// Speed multiplier (shift).
    pub boost: bool,
    /// The point under the cursor (lat, lon in degrees, altitude in
    /// metres), if the cursor ray meets the ground: the wheel zooms
    /// towards it.
    pub zoom_at: Option<(f64, f64, f64)>,
}

/// Elevation in metres of the resident ground at geodetic `(lat, lon)`
/// (degrees): the deepest resident elevation block holding it, bilinear in
/// its grid at the LOD it has (LOD 1: the even samples only).
pub fn ground_elevation(tree: &PartialTree, header: &Header, lat: f64, lon: f64) -> Option<f64> {
    let fc = FaceCoord::from_lat_lon(lat.to_radians(), lon.to_radians());
    let et = tree.elevation();
    let w = et.width;
    let side = w + 1;
    let mut best = None;
    for level in 0..=planet_core::block::MAX_LEVEL {
        let n = (1u64 << level) as f64;
        let cell = |c: f64| ((c * n).floor().max(0.0) as u64).min((1u64 << level) - 1);
        let (x, y) = (cell(fc.s), cell(fc.t));
        let Some(id) = BlockId::new(fc.face, level, x as u32, y as u32) else {
            break;
        };
        let Some(node) = et.get(&id) else { break };
        if let Some(Samples::Elevation(g)) = node.samples.as_ref() {
            if g.len() == side * side {
                let step = if node.lod == 0 { 1 } else { 2 };
                let fi = ((fc.s * n - x as f64) * w as f64).clamp(0.0, w as f64);
                let fj = ((fc.t * n - y as f64) * w as f64).clamp(0.0, w as f64);
                let (i0, j0) = (
                    ((fi as usize) / step * step).min(w - step),
                    ((fj as usize) / step * step).min(w - step),
                );
                let (u, v) = (
                    (fi - i0 as f64) / step as f64,
                    (fj - j0 as f64) / step as f64,
                );
                let at = |i: usize, j: usize| g[j * side + i] as f64;
                let q = at(i0, j0) * (1.0 - u) * (1.0 - v)
                    + at(i0 + step, j0) * u * (1.0 - v)
                    + at(i0, j0 + step) * (1.0 - u) * v
                    + at(i0 + step, j0 + step) * u * v;
                best = Some(q * header.elevation_scale as f64 + header.elevation_offset as f64);
            }
        }
        if !node.split {
            break;
        }
    }
    best
}

/// Where the ray through pixel `(x, y)` of a `width × height` view of
/// `camera` meets the ground, approximated by the sphere through the ground
/// below the eye at altitude `ground_alt` (the datum's radius there plus
/// that altitude): `None` when the ray misses it or the eye is below it.
pub fn pick(
    datum: &Datum,
    camera: &Camera,
    x: f64,
    y: f64,
    width: u32,
    height: u32,
    ground_alt: f64,
) -> Option<DVec3> {
    let (w, h) = (width.max(1) as f64, height.max(1) as f64);
    let fwd = camera.forward.normalize();
    let right = fwd.cross(camera.up).normalize();
    let up = right.cross(fwd);
    let ty = (camera.fov_y * 0.5).tan();
    let tx = ty * camera.aspect;
    let ndc = (2.0 * x / w - 1.0, 1.0 - 2.0 * y / h);
    let dir = (fwd + right * (ndc.0 * tx) + up * (ndc.1 * ty)).normalize();
    let eye = camera.eye;
    let (_, _, alt) = position_to_geodetic(datum, eye);
    let r = eye.length() - alt + ground_alt;
    if r.is_nan() || r <= 0.0 || eye.length() <= r {
        return None;
    }
    // |eye + t·dir| = r, nearest t > 0 (relative form: no cancellation of
    // |eye|² − r² at planet scale beyond f64's 1e-16).
    let b = eye.dot(dir);
    let c = (eye.length() - r) * (eye.length() + r);
    let disc = b * b - c;
    if disc.is_nan() || disc < 0.0 {
        return None;
    }
    let t = -b - disc.sqrt();
    (t.is_finite() && t > 0.0).then(|| eye + dir * t)
}

impl Controller {
    /// Orbiting `(lat, lon)` from `range` metres, looking straight down.
    pub fn orbit(lat: f64, lon: f64, range: f64) -> Controller {
        Controller {
            mode: Mode::Orbit,
            lat,
            lon,
            alt: range,
            heading: 0.0,
            pitch: -90.0,
            target_lat: lat,
            target_lon: lon,
            target_alt: 0.0,
            range,
            azimuth: 180.0,
            tilt: 0.0,
        }
    }

    /// Flying at `(lat, lon, alt)`, heading north, looking 20° down.
    pub fn fly(lat: f64, lon: f64, alt: f64) -> Controller {
        Controller {
            mode: Mode::Fly,
            lat,
            lon,
            alt,
            heading: 0.0,
            pitch: -20.0,
            target_lat: lat,
            target_lon: lon,
            target_alt: 0.0,
            range: alt.abs().max(100.0),
            azimuth: 180.0,
            tilt: 0.0,
        }
    }

    /// A view of a named place: flying 6 km above the datum, south of the
    /// place, heading north and looking 20° down so that the place is at
    /// the centre of the view.
    pub fn place(lat: f64, lon: f64) -> Controller {
        const ALT: f64 = 6000.0;
        const PITCH: f64 = -20.0;
        // Ground distance to the point the view's centre ray meets
        // (flat-ground approximation, about 16.5 km; 1 km of error at most).
        let ahead = ALT / (-PITCH).to_radians().tan();
        let dlat = (ahead / 6_371_000.0).to_degrees();
        Controller {
            pitch: PITCH,
            ..Controller::fly((lat - dlat).clamp(-89.9, 89.9), lon, ALT)
        }
    }

    /// Eye, forward and up vectors.
    pub fn pose(&self, datum: &Datum) -> (DVec3, DVec3, DVec3) {
        match self.mode {
            Mode::Fly => {
                let eye = geodetic_to_position(datum, self.lat, self.lon, self.alt);
                let (up, east, north) = local_frame(self.lat, self.lon);
                let (h, p) = (self.heading.to_radians(), self.pitch.to_radians());
                let hor = north * h.cos() + east * h.sin();
                let fwd = hor * p.cos() + up * p.sin();
                let cam_up = -hor * p.sin() + up * p.cos();
                (eye, fwd, cam_up)
            }
            Mode::Orbit => {
                let target =
                    geodetic_to_position(datum, self.target_lat, self.target_lon, self.target_alt);
                let (up, east, north) = local_frame(self.target_lat, self.target_lon);
                let (a, t) = (self.azimuth.to_radians(), self.tilt.to_radians());
                let h = north * a.cos() + east * a.sin();
                let off = h * t.sin() + up * t.cos();
                let eye = target + off * self.range;
                let fwd = -off;
                let cam_up = -h * t.cos() + up * t.sin();
                (eye, fwd, cam_up)
            }
        }
    }

    /// The client camera for a viewport.
    pub fn camera(&self, datum: &Datum, width: u32, height: u32) -> Camera {
        let (eye, fwd, up) = self.pose(datum);
        Camera {
            eye,
            forward: fwd,
            up,
            fov_y: FOV_Y,
            aspect: width as f64 / height.max(1) as f64,
            viewport_height_px: height.max(1) as f64,
        }
    }

    /// Altitude of the eye above the datum (metres).
    pub fn altitude(&self, datum: &Datum) -> f64 {
        match self.mode {
            Mode::Fly => self.alt,
            Mode::Orbit => position_to_geodetic(datum, self.pose(datum).0).2,
        }
    }

    /// Switch fly ↔ orbit keeping the view (orbit targets the point the view
    /// ray hits on the datum sphere, or the point below).
    pub fn toggle(&mut self, datum: &Datum) {
        let (eye, fwd, _) = self.pose(datum);
        let fwd = fwd.normalize();
        match self.mode {
            Mode::Orbit => {
                let (lat, lon, alt) = position_to_geodetic(datum, eye);
                let (up, east, north) = local_frame(lat, lon);
                self.lat = lat;
                self.lon = lon;
                self.alt = alt;
                self.pitch = fwd
                    .dot(up)
                    .clamp(-1.0, 1.0)
                    .asin()
                    .to_degrees()
                    .clamp(-89.0, 89.0);
                let hz = fwd - up * fwd.dot(up);
                self.heading = if hz.length() > 1e-6 {
                    hz.dot(east).atan2(hz.dot(north)).to_degrees()
                } else {
                    (self.azimuth + 180.0) % 360.0
                };
                self.mode = Mode::Fly;
            }
            Mode::Fly => {
                let (lat, lon, alt) = position_to_geodetic(datum, eye);
                // The sphere through the ground below the eye.
                let r = eye.length() - alt;
                let b = eye.dot(fwd);
                let disc = b * b - (eye.length_squared() - r * r);
                let hit = if disc > 0.0 {
                    let t = -b - disc.sqrt();
                    (t > 0.0).then_some(t)
                } else {
                    None
                };
                match hit {
                    Some(t) => {
                        let p = eye + fwd * t;
                        let (tl, tn, ta) = position_to_geodetic(datum, p);
                        let (up, east, north) = local_frame(tl, tn);
                        let off = (-fwd).normalize();
                        self.target_lat = tl;
                        self.target_lon = tn;
                        self.target_alt = ta;
                        self.range = t;
                        self.tilt = off.dot(up).clamp(-1.0, 1.0).acos().to_degrees().min(89.0);
                        self.azimuth = off.dot(east).atan2(off.dot(north)).to_degrees();
                    }
                    None => {
                        self.target_lat = lat;
                        self.target_lon = lon;
                        self.target_alt = 0.0;
                        self.range = alt.max(100.0);
                        self.tilt = 0.0;
                        self.azimuth = self.heading + 180.0;
                    }
                }
                self.mode = Mode::Orbit;
            }
        }
    }

    /// Apply one frame of input over `dt` seconds.
    pub fn update(&mut self, datum: &Datum, input: &Input, dt: f64) {
        let r = datum.equatorial_radius();
        let boost = if input.boost { 5.0 } else { 1.0 };
        let dt = dt.clamp(0.0, 0.25);
        match self.mode {
            Mode::Fly => {
                // Speed proportional to altitude: cross it in about a second.
                let speed = self.alt.abs().max(20.0) * boost;
                self.heading += input.drag.0 * 0.2;
                self.pitch = (self.pitch - input.drag.1 * 0.2).clamp(-89.0, 89.0);
                let (h, p) = (self.heading.to_radians(), self.pitch.to_radians());
                let step = speed * dt;
                // Forward follows the view (diving works); right is level.
                let dn = step * (input.forward * p.cos() * h.cos() - input.right * h.sin());
                let de = step * (input.forward * p.cos() * h.sin() + input.right * h.cos());
                let du = step * (input.forward * p.sin() + input.up);
                let rr = r + self.alt;
                self.lat = (self.lat + (dn / rr).to_degrees()).clamp(-89.9, 89.9);
                self.lon += (de / (rr * self.lat.to_radians().cos().max(1e-3))).to_degrees();
                self.alt += du;
                if input.scroll != 0.0 {
                    // Towards the point under the cursor (or straight down).
                    let k = 1.0 - 0.9f64.powf(input.scroll);
                    match input.zoom_at {
                        Some((zlat, zlon, zalt)) => {
                            self.lat = (self.lat + (zlat - self.lat) * k).clamp(-89.9, 89.9);
                            let dlon = (zlon - self.lon + 540.0).rem_euclid(360.0) - 180.0;
                            self.lon += dlon * k;
                            self.alt += (zalt - self.alt) * k;
                        }
                        None => self.alt *= 1.0 - k,
                    }
                }
                self.alt = self.alt.clamp(2.0, 20.0 * r);
            }
            Mode::Orbit => {
                self.azimuth += input.drag.0 * 0.3;
                self.tilt = (self.tilt + input.drag.1 * 0.2).clamp(0.0, 89.0);
                let speed = self.range.max(20.0) * boost * 0.5;
                let a = (self.azimuth + 180.0).to_radians();
                let step = speed * dt;
                let dn = step * (input.forward * a.cos() - input.right * a.sin());
                let de = step * (input.forward * a.sin() + input.right * a.cos());
                self.target_lat = (self.target_lat + (dn / r).to_degrees()).clamp(-89.9, 89.9);
                self.target_lon +=
                    (de / (r * self.target_lat.to_radians().cos().max(1e-3))).to_degrees();
                let zoom = input.scroll - input.up * dt * 2.0;
                if zoom != 0.0 {
                    self.range *= 0.9f64.powf(zoom);
                }
                if let (Some((zlat, zlon, _)), true) = (input.zoom_at, input.scroll != 0.0) {
                    // The target moves towards the point under the cursor
                    // as much as the range shrinks.
                    let k = 1.0 - 0.9f64.powf(input.scroll);
                    self.target_lat =
                        (self.target_lat + (zlat - self.target_lat) * k).clamp(-89.9, 89.9);
                    let dlon = (zlon - self.target_lon + 540.0).rem_euclid(360.0) - 180.0;
                    self.target_lon += dlon * k;
                }
                self.range = self.range.clamp(5.0, 20.0 * r);
            }
        }
        self.lon = (self.lon + 540.0).rem_euclid(360.0) - 180.0;
        self.target_lon = (self.target_lon + 540.0).rem_euclid(360.0) - 180.0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn geodetic_round_trip() {
        let d = Datum::WGS84;
        for (lat, lon, alt) in [
            (46.85, -121.76, 4392.0),
            (-33.0, 151.0, 1.0e6),
            (89.0, 10.0, 50.0),
        ] {
            let p = geodetic_to_position(&d, lat, lon, alt);
            let (a, b, c) = position_to_geodetic(&d, p);
            assert!((a - lat).abs() < 1e-7 && (b - lon).abs() < 1e-7, "{a} {b}");
            assert!((c - alt).abs() < 1e-3, "{c} {alt}");
        }
    }

    #[test]
    fn toggle_keeps_the_view() {
        let d = Datum::WGS84;
        let mut c = Controller::fly(46.8, -121.9, 3000.0);
        c.heading = 80.0;
        c.pitch = -15.0;
        let (e0, f0, _) = c.pose(&d);
        c.toggle(&d);
        assert_eq!(c.mode, Mode::Orbit);
        let (e1, f1, _) = c.pose(&d);
        assert!((e0 - e1).length() < 1.0, "{}", (e0 - e1).length());
        assert!(f0.normalize().dot(f1.normalize()) > 0.9999);
        c.toggle(&d);
        let (e2, f2, _) = c.pose(&d);
        assert!((e0 - e2).length() < 1.0);
        assert!(f0.normalize().dot(f2.normalize()) > 0.9999);
    }

    #[test]
    fn orbit_looks_at_target_and_moves() {
        let d = Datum::WGS84;
        let mut c = Controller::orbit(10.0, 20.0, 1.0e7);
        let (eye, fwd, up) = c.pose(&d);
        assert!(eye.length() > 1.6e7);
        assert!(fwd.normalize().dot(-eye.normalize()) > 0.99);
        assert!(up.dot(fwd).abs() < 1e-9);
        c.update(
            &d,
            &Input {
                forward: 1.0,
                ..Input::default()
            },
            0.1,
        );
        assert!(c.target_lat > 10.0);
    }

    #[test]
    fn pick_finds_the_ground_under_the_cursor_at_every_scale() {
        let d = Datum::WGS84;
        for (lat, lon, alt) in [
            (46.85, -121.76, 1.0),
            (89.99, 10.0, 5000.0),
            (0.0, 180.0, 1.0e6),
            (-45.0, 45.0, 1000.0 * 6.4e6),
        ] {
            let c = Controller {
                pitch: -90.0,
                ..Controller::fly(lat, lon, alt)
            };
            let cam = c.camera(&d, 640, 480);
            // The centre pixel: the point straight below, on the ground.
            let p = pick(&d, &cam, 320.0, 240.0, 640, 480, 0.0).expect("centre hits");
            let (plat, plon, palt) = position_to_geodetic(&d, p);
            assert!(
                palt.abs() < 1e-3 * alt.max(1.0),
                "{lat} {lon} {alt}: alt {palt}"
            );
            let tol = 1e-6 + 1e-9 * alt;
            let dlon = ((plon - lon + 540.0).rem_euclid(360.0) - 180.0).abs();
            assert!(
                (plat - lat).abs() < tol.max(1e-4) && (dlon < tol.max(1e-4) || lat.abs() > 89.9),
                "{lat} {lon} {alt}: {plat} {plon}"
            );
            // A ground 500 m higher is met sooner.
            if alt > 600.0 {
                let q = pick(&d, &cam, 320.0, 240.0, 640, 480, 500.0).expect("hits");
                assert!((q - cam.eye).length() < (p - cam.eye).length());
            }
        }
        // Looking at the sky, and from inside the planet: nothing.
        let up = Controller {
            pitch: 80.0,
            ..Controller::fly(10.0, 20.0, 100.0)
        };
        assert!(pick(&d, &up.camera(&d, 640, 480), 320.0, 240.0, 640, 480, 0.0).is_none());
        let inside = Controller::fly(10.0, 20.0, -5000.0);
        assert!(pick(
            &d,
            &inside.camera(&d, 640, 480),
            320.0,
            240.0,
            640,
            480,
            0.0
        )
        .is_none());
        // A corner pixel of a view straight down is off-centre, to the side
        // the pixel is on (top-left: north-west when heading north).
        let c = Controller {
            pitch: -90.0,
            ..Controller::fly(0.0, 0.0, 10_000.0)
        };
        let cam = c.camera(&d, 640, 480);
        let p = pick(&d, &cam, 0.0, 0.0, 640, 480, 0.0).expect("corner hits");
        let (plat, plon, _) = position_to_geodetic(&d, p);
        assert!(plat > 0.0 && plon < 0.0, "{plat} {plon}");
    }

    #[test]
    fn the_wheel_zooms_towards_the_point_under_the_cursor() {
        let d = Datum::WGS84;
        let mut c = Controller::fly(0.0, 0.0, 10_000.0);
        let input = Input {
            scroll: 3.0,
            zoom_at: Some((0.1, -0.1, 500.0)),
            ..Input::default()
        };
        c.update(&d, &input, 0.0);
        let k = 1.0 - 0.9f64.powi(3);
        assert!((c.lat - 0.1 * k).abs() < 1e-12 && (c.lon + 0.1 * k).abs() < 1e-12);
        assert!((c.alt - (10_000.0 + (500.0 - 10_000.0) * k)).abs() < 1e-6);
        // Across the antimeridian the short way.
        let mut c = Controller::fly(0.0, 179.9, 10_000.0);
        let input = Input {
            scroll: 1.0,
            zoom_at: Some((0.0, -179.9, 0.0)),
            ..Input::default()
        };
        c.update(&d, &input, 0.0);
        assert!(c.lon > 179.9 || c.lon < -179.9, "{}", c.lon);
        // Orbit: the target follows the cursor as the range shrinks.
        let mut o = Controller::orbit(10.0, 10.0, 1.0e6);
        let input = Input {
            scroll: 2.0,
            zoom_at: Some((11.0, 10.0, 0.0)),
            ..Input::default()
        };
        o.update(&d, &input, 0.0);
        assert!(o.target_lat > 10.0 && o.range < 1.0e6);
    }
}
