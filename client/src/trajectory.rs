//! Camera trajectories: keyframes in geodetic coordinates, interpolated into
//! [`Camera`]s (for the viewer's scripted flights and the flight benchmark).
//!
//! Text format: one keyframe per line, `t lat lon alt heading pitch`
//! (seconds, degrees, degrees, metres above the datum, degrees clockwise
//! from north, degrees above the horizontal: −90 looks straight down),
//! whitespace separated; `#` starts a comment; blank lines are ignored; `t`
//! strictly increasing.
//!
//! Interpolation between the two keyframes around `t` is linear in latitude,
//! pitch and (the shortest way round, across the antimeridian) longitude and
//! heading; altitude is interpolated logarithmically when both ends are
//! positive and differ by more than a factor of 2 (so a descent from orbit
//! covers each decade of altitude in equal time), linearly otherwise. Before
//! the first keyframe and after the last the camera holds still.
//!
//! The camera frame is built from the local east/north/up frame of the
//! geodetic normal, with east taken from the longitude (so it stays defined
//! at the poles), and the up vector is the heading direction rotated by the
//! pitch, which is always orthogonal to the view direction (also when
//! looking straight down).

use crate::visibility::Camera;
use glam::DVec3;
use planet_core::cube::direction_from_lat_lon;
use planet_core::Datum;
use std::path::Path;
use thiserror::Error;

/// One keyframe.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Keyframe {
    /// Time in seconds.
    pub t: f64,
    /// Geodetic latitude in degrees.
    pub lat_deg: f64,
    /// Longitude in degrees.
    pub lon_deg: f64,
    /// Height above the datum in metres.
    pub alt_m: f64,
    /// Heading in degrees, 0 = north, clockwise.
    pub heading_deg: f64,
    /// Pitch in degrees, 0 = horizontal, −90 = straight down.
    pub pitch_deg: f64,
}

/// A trajectory: keyframes with strictly increasing times.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    /// The keyframes.
    pub keyframes: Vec<Keyframe>,
}

/// Why a trajectory cannot be read.
#[derive(Debug, Error)]
pub enum TrajectoryError {
    /// The file cannot be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The path.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A line does not hold six numbers.
    #[error("line {line}: {reason}")]
    Syntax {
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        reason: String,
    },
    /// Times are not strictly increasing.
    #[error("line {line}: time {t} is not after the previous keyframe's")]
    NotIncreasing {
        /// 1-based line number.
        line: usize,
        /// The offending time.
        t: f64,
    },
    /// No keyframe at all.
    #[error("no keyframes")]
    Empty,
    /// Neither a built-in name nor an existing file.
    #[error("no built-in trajectory {spec:?} ({names}) and no such file", names = BUILTIN_NAMES.join(", "))]
    NotFound {
        /// The name or path given.
        spec: String,
    },
}

/// The built-in trajectories: each name with `bench/trajectories/NAME.txt`,
/// compiled in.
const BUILTINS: [(&str, &str); 11] = [
    (
        "rainier",
        include_str!("../../bench/trajectories/rainier.txt"),
    ),
    (
        "everest",
        include_str!("../../bench/trajectories/everest.txt"),
    ),
    ("orbit", include_str!("../../bench/trajectories/orbit.txt")),
    (
        "static-low",
        include_str!("../../bench/trajectories/static-low.txt"),
    ),
    (
        "low-pass",
        include_str!("../../bench/trajectories/low-pass.txt"),
    ),
    (
        "glide-rainier",
        include_str!("../../bench/trajectories/glide-rainier.txt"),
    ),
    (
        "corner-pass",
        include_str!("../../bench/trajectories/corner-pass.txt"),
    ),
    (
        "khumbu",
        include_str!("../../bench/trajectories/khumbu.txt"),
    ),
    (
        "edge-pass",
        include_str!("../../bench/trajectories/edge-pass.txt"),
    ),
    (
        "circle-rainier",
        include_str!("../../bench/trajectories/circle-rainier.txt"),
    ),
    (
        "cross-rainier",
        include_str!("../../bench/trajectories/cross-rainier.txt"),
    ),
];

/// Names accepted by [`Trajectory::builtin`].
pub const BUILTIN_NAMES: [&str; BUILTINS.len()] = {
    let mut names = [""; BUILTINS.len()];
    let mut i = 0;
    while i < names.len() {
        names[i] = BUILTINS[i].0;
        i += 1;
    }
    names
};

/// The help of a `--trajectory` option (`planet-bench flight`,
/// `planet-view render`): every name of [`BUILTIN_NAMES`] (a test checks
/// it), or a file.
pub const TRAJECTORY_HELP: &str = "Built-in trajectory (rainier, everest, orbit, static-low, \
    low-pass, glide-rainier, corner-pass, khumbu, edge-pass, circle-rainier, cross-rainier) or a \
    trajectory file";

/// Mount Rainier summit (degrees).
pub const RAINIER: (f64, f64) = (46.853, -121.760);
/// Mount Everest summit (degrees).
pub const EVEREST: (f64, f64) = (27.988, 86.925);

/// The text of a built-in trajectory: `bench/trajectories/NAME.txt`,
/// compiled in.
pub fn builtin_text(name: &str) -> Option<&'static str> {
    BUILTINS.iter().find(|(n, _)| *n == name).map(|(_, t)| *t)
}

fn wrap180(d: f64) -> f64 {
    let r = (d + 180.0).rem_euclid(360.0) - 180.0;
    if r.is_finite() {
        r
    } else {
        0.0
    }
}

impl Trajectory {
    /// Parse the text format (see the module documentation).
    pub fn parse(text: &str) -> Result<Trajectory, TrajectoryError> {
        let mut keyframes: Vec<Keyframe> = Vec::new();
        for (n, raw) in text.lines().enumerate() {
            let line = n + 1;
            let content = raw.split('#').next().unwrap_or("").trim();
            if content.is_empty() {
                continue;
            }
            let fields: Vec<&str> = content.split_whitespace().collect();
            if fields.len() != 6 {
                return Err(TrajectoryError::Syntax {
                    line,
                    reason: format!(
                        "expected 6 numbers (t lat lon alt heading pitch), got {}",
                        fields.len()
                    ),
                });
            }
            let mut v = [0.0f64; 6];
            for (slot, f) in v.iter_mut().zip(&fields) {
                *slot = f.parse::<f64>().map_err(|_| TrajectoryError::Syntax {
                    line,
                    reason: format!("{f:?} is not a number"),
                })?;
                if !slot.is_finite() {
                    return Err(TrajectoryError::Syntax {
                        line,
                        reason: format!("{f:?} is not finite"),
                    });
                }
            }
            let k = Keyframe {
                t: v[0],
                lat_deg: v[1],
                lon_deg: v[2],
                alt_m: v[3],
                heading_deg: v[4],
                pitch_deg: v[5],
            };
            if !(-90.0..=90.0).contains(&k.lat_deg) {
                return Err(TrajectoryError::Syntax {
                    line,
                    reason: format!("latitude {} outside [-90, 90]", k.lat_deg),
                });
            }
            if !(-90.0..=90.0).contains(&k.pitch_deg) {
                return Err(TrajectoryError::Syntax {
                    line,
                    reason: format!("pitch {} outside [-90, 90]", k.pitch_deg),
                });
            }
            if let Some(prev) = keyframes.last() {
                if k.t <= prev.t {
                    return Err(TrajectoryError::NotIncreasing { line, t: k.t });
                }
            }
            keyframes.push(k);
        }
        if keyframes.is_empty() {
            return Err(TrajectoryError::Empty);
        }
        Ok(Trajectory { keyframes })
    }

    /// Read and parse a file.
    pub fn load(path: &Path) -> Result<Trajectory, TrajectoryError> {
        let text = std::fs::read_to_string(path).map_err(|source| TrajectoryError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Trajectory::parse(&text)
    }

    /// A built-in trajectory, one of [`BUILTIN_NAMES`].
    pub fn builtin(name: &str) -> Option<Trajectory> {
        builtin_text(name).and_then(|t| Trajectory::parse(t).ok())
    }

    /// What a command line's `--trajectory` names: a built-in trajectory,
    /// else a file.
    pub fn from_spec(spec: &str) -> Result<Trajectory, TrajectoryError> {
        if let Some(t) = Trajectory::builtin(spec) {
            return Ok(t);
        }
        let path = Path::new(spec);
        if !path.exists() {
            return Err(TrajectoryError::NotFound { spec: spec.into() });
        }
        Trajectory::load(path)
    }

    /// Time of the last keyframe (0 for a single keyframe).
    pub fn duration(&self) -> f64 {
        self.keyframes.last().map_or(0.0, |k| k.t)
    }

    /// The interpolated keyframe at time `t` (clamped to the trajectory).
    pub fn keyframe_at(&self, t: f64) -> Keyframe {
        let ks = &self.keyframes;
        let Some(first) = ks.first() else {
            return Keyframe {
                t,
                lat_deg: 0.0,
                lon_deg: 0.0,
                alt_m: 2.0e7,
                heading_deg: 0.0,
                pitch_deg: -90.0,
            };
        };
        let last = ks[ks.len() - 1];
        // `t <= first.t`, or NaN: clamp to the first keyframe.
        if t.partial_cmp(&first.t) != Some(std::cmp::Ordering::Greater) {
            return Keyframe { t, ..*first };
        }
        if t >= last.t {
            return Keyframe { t, ..last };
        }
        // First keyframe strictly after t.
        let i = ks.partition_point(|k| k.t <= t);
        let (a, b) = (ks[i - 1], ks[i]);
        let u = ((t - a.t) / (b.t - a.t)).clamp(0.0, 1.0);
        let lerp = |x: f64, y: f64| x + (y - x) * u;
        let alt = if a.alt_m > 0.0 && b.alt_m > 0.0 && {
            let r = b.alt_m / a.alt_m;
            !(0.5..=2.0).contains(&r)
        } {
            (a.alt_m.ln() + (b.alt_m.ln() - a.alt_m.ln()) * u).exp()
        } else {
            lerp(a.alt_m, b.alt_m)
        };
        Keyframe {
            t,
            lat_deg: lerp(a.lat_deg, b.lat_deg),
            lon_deg: wrap180(a.lon_deg + wrap180(b.lon_deg - a.lon_deg) * u),
            alt_m: alt,
            heading_deg: wrap180(a.heading_deg + wrap180(b.heading_deg - a.heading_deg) * u),
            pitch_deg: lerp(a.pitch_deg, b.pitch_deg),
        }
    }

    /// The camera at time `t` above `datum`.
    pub fn camera_at(
        &self,
        t: f64,
        datum: &Datum,
        fov_y: f64,
        aspect: f64,
        viewport_height_px: f64,
    ) -> Camera {
        camera_from_keyframe(
            &self.keyframe_at(t),
            datum,
            fov_y,
            aspect,
            viewport_height_px,
        )
    }
}

/// The local (east, north, up) frame at a geodetic latitude and longitude
/// (radians). East comes from the longitude, so it is defined at the poles.
pub fn enu_frame(lat: f64, lon: f64) -> (DVec3, DVec3, DVec3) {
    let (sl, cl) = lat.sin_cos();
    let (so, co) = lon.sin_cos();
    let east = DVec3::new(-so, co, 0.0);
    let north = DVec3::new(-sl * co, -sl * so, cl);
    let up = DVec3::new(cl * co, cl * so, sl);
    (east, north, up)
}

/// The camera of one keyframe.
pub fn camera_from_keyframe(
    k: &Keyframe,
    datum: &Datum,
    fov_y: f64,
    aspect: f64,
    viewport_height_px: f64,
) -> Camera {
    let (lat, lon) = (k.lat_deg.to_radians(), k.lon_deg.to_radians());
    let eye = DVec3::from_array(datum.position(direction_from_lat_lon(lat, lon), k.alt_m));
    let (east, north, up) = enu_frame(lat, lon);
    let (sh, ch) = k.heading_deg.to_radians().sin_cos();
    let horizontal = north * ch + east * sh;
    let (sp, cp) = k.pitch_deg.clamp(-90.0, 90.0).to_radians().sin_cos();
    let forward = horizontal * cp + up * sp;
    let cam_up = up * cp - horizontal * sp;
    Camera {
        eye,
        forward,
        up: cam_up,
        fov_y,
        aspect,
        viewport_height_px,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::visibility::Basis;

    #[test]
    fn builtins_parse_and_files_match() {
        for name in BUILTIN_NAMES {
            let t = Trajectory::builtin(name).expect(name);
            assert!(t.duration() > 0.0);
            assert!(TRAJECTORY_HELP.contains(name), "{name} not in the help");
        }
        assert!(Trajectory::builtin("nope").is_none());
        // A command line's spec: a name, a file, or an error naming both.
        assert_eq!(
            Trajectory::from_spec("khumbu").unwrap().keyframes,
            Trajectory::builtin("khumbu").unwrap().keyframes
        );
        let e = Trajectory::from_spec("/nonexistent/nope.txt").unwrap_err();
        assert!(matches!(e, TrajectoryError::NotFound { .. }), "{e}");
        assert!(
            e.to_string().contains("circle-rainier, cross-rainier"),
            "{e}"
        );
        let dir = std::env::temp_dir().join(format!("traj-spec-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("t.txt");
        std::fs::write(&file, "0 1 2 1000 0 -90\n5 1 2 2000 0 -90\n").unwrap();
        assert_eq!(
            Trajectory::from_spec(file.to_str().unwrap())
                .unwrap()
                .keyframes
                .len(),
            2
        );
        std::fs::remove_dir_all(&dir).unwrap();
        // The rainier flight: orbit, a stop of at least 10 s, ≥ 300 m/s.
        let r = Trajectory::builtin("rainier").unwrap();
        assert!(r.keyframes[0].alt_m >= 1.9e7);
        let d = Datum::WGS84;
        let speed = |t: f64| {
            let a = r.camera_at(t, &d, 1.0, 1.0, 100.0).eye;
            let b = r.camera_at(t + 0.1, &d, 1.0, 1.0, 100.0).eye;
            (b - a).length() / 0.1
        };
        assert!(speed(40.0) >= 300.0 && speed(58.0) >= 300.0);
        assert_eq!(speed(25.0), 0.0);
        assert_eq!(speed(33.0), 0.0);
    }

    #[test]
    fn parse_errors() {
        assert!(matches!(
            Trajectory::parse("# nothing\n"),
            Err(TrajectoryError::Empty)
        ));
        assert!(matches!(
            Trajectory::parse("0 0 0 1 0 0\n0 0 0 1 0 0\n"),
            Err(TrajectoryError::NotIncreasing { line: 2, .. })
        ));
        assert!(matches!(
            Trajectory::parse("0 0 0 1 0\n"),
            Err(TrajectoryError::Syntax { line: 1, .. })
        ));
        assert!(matches!(
            Trajectory::parse("0 0 x 1 0 0\n"),
            Err(TrajectoryError::Syntax { .. })
        ));
        let t = Trajectory::parse("  # c\n0 1 2 3 4 5 # trailing\n\n1 1 2 3 4 5\n").unwrap();
        assert_eq!(t.keyframes.len(), 2);
    }

    #[test]
    fn interpolation() {
        let t = Trajectory::parse("0 0 170 1000000 350 -90\n10 10 -170 1000 10 0\n").unwrap();
        let k = t.keyframe_at(5.0);
        assert!((k.lat_deg - 5.0).abs() < 1e-12);
        assert!((k.lon_deg.abs() - 180.0).abs() < 1e-9, "{}", k.lon_deg);
        assert!(k.heading_deg.abs() < 1e-9, "{}", k.heading_deg);
        assert!((k.alt_m - 31622.776).abs() < 1e-2, "{}", k.alt_m);
        assert_eq!(t.keyframe_at(-1.0).lat_deg, 0.0);
        assert_eq!(t.keyframe_at(99.0).lat_deg, 10.0);
    }

    #[test]
    fn camera_frames_are_sane() {
        let d = Datum::WGS84;
        for (lat, lon, h, p) in [
            (90.0, 0.0, 0.0, -90.0),
            (-90.0, 45.0, 90.0, 0.0),
            (46.8, -121.7, 0.0, -90.0),
            (0.0, 180.0, 270.0, -15.0),
        ] {
            let k = Keyframe {
                t: 0.0,
                lat_deg: lat,
                lon_deg: lon,
                alt_m: 1000.0,
                heading_deg: h,
                pitch_deg: p,
            };
            let c = camera_from_keyframe(&k, &d, 1.0, 1.5, 720.0);
            let Basis {
                forward: f,
                right: r,
                up: u,
            } = c.basis();
            assert!(f.is_finite() && r.is_finite() && u.is_finite());
            assert!(c.forward.dot(c.up).abs() < 1e-9);
            assert!((c.up.length() - 1.0).abs() < 1e-9);
            let n = c.eye.normalize();
            // pitch: angle of the view direction above the horizontal
            let pitch = f.dot(n).asin().to_degrees();
            assert!((pitch - p).abs() < 0.3, "{pitch} vs {p}");
        }
        // Heading 90 at the equator looks east (+Y at lon 0).
        let k = Keyframe {
            t: 0.0,
            lat_deg: 0.0,
            lon_deg: 0.0,
            alt_m: 10.0,
            heading_deg: 90.0,
            pitch_deg: 0.0,
        };
        let c = camera_from_keyframe(&k, &d, 1.0, 1.0, 100.0);
        assert!((c.forward - DVec3::Y).length() < 1e-12);
    }
}
