//! Camera geometry and the interactive fly / orbit controller.
//!
//! Positions are planet-centred f64 metres. Local frames use the geodetic
//! normal of the datum (`direction_from_lat_lon`), east and north.

use glam::DVec3;
use planet_client::Camera;
use planet_core::cube::direction_from_lat_lon;
use planet_core::Datum;
use planet_view::CameraF64;

/// Vertical field of view of the viewer (radians).
pub const FOV_Y: f64 = 1.0;

/// The renderer's camera for the client's.
pub fn to_render(c: &Camera) -> CameraF64 {
    CameraF64 {
        position: c.eye.to_array(),
        forward: c.forward.to_array(),
        up: c.up.to_array(),
        fov_y: c.fov_y,
    }
}

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
                    self.alt *= 0.9f64.powf(input.scroll);
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
}
