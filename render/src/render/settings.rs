//! What the renderer is told once: radii, lighting, the atmosphere.

use super::*;

/// Renderer settings.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderSettings {
    /// Use the edge strips (false: every edge at level difference 0, which
    /// shows cracks; for tests and demonstrations).
    pub crack_fixing: bool,
    /// Near/far plane choice.
    pub depth_mode: DepthMode,
    /// Minimum planet radius (datum polar radius + minimum elevation).
    ///
    /// The far plane assumes nothing drawn lies below this radius. Coarse
    /// blocks' flat triangles dip below their vertices (chord sag, about
    /// `R·θ²/8` for a triangle spanning the angle `θ`: 4 km for a level-2
    /// block at LOD 1 with `W = 16`), so subtract the sag of the coarsest
    /// drawn blocks or distant coarse terrain may be cut at the horizon.
    pub r_min: f64,
    /// Maximum planet radius (datum equatorial radius + maximum elevation).
    pub r_max: f64,
    /// Direction towards the sun (planet frame).
    pub sun_dir: [f32; 3],
    /// Ambient light fraction.
    pub ambient: f32,
    /// Background colour (linear RGBA) of space; with an [`Atmosphere`],
    /// the sky's colour inside the air ([`Atmosphere::sky`]).
    pub clear: [f64; 4],
    /// The datum's semi-axes (equatorial, polar) in metres: the eye's
    /// altitude for the sky's colour.
    pub radii: [f64; 2],
    /// Aerial perspective ([`Atmosphere`]); `None`: none.
    pub atmosphere: Option<Atmosphere>,
    /// Evict cached GPU meshes and textures not drawn for this many frames.
    pub cache_frames: u64,
}

impl RenderSettings {
    /// Settings for a planet with `datum` and elevations in `[min, max]` m.
    pub fn for_planet(datum: &planet_core::Datum, min_elev: f64, max_elev: f64) -> RenderSettings {
        RenderSettings {
            crack_fixing: true,
            depth_mode: DepthMode::Horizon,
            r_min: datum.polar_radius() + min_elev,
            r_max: datum.equatorial_radius() + max_elev,
            radii: [datum.equatorial_radius(), datum.polar_radius()],
            sun_dir: [0.6, 0.5, 0.62],
            ambient: 0.25,
            clear: [0.0, 0.0, 0.02, 1.0],
            atmosphere: Some(Atmosphere::EARTH),
            cache_frames: 8,
        }
    }
}

/// Aerial perspective: terrain fades towards a sunlit sky colour with the
/// air between it and the eye. The optical depth is that of an exponential
/// atmosphere near the seen point, `ρ(h)·L / V` with `ρ(h) = exp(−h/H)`
/// and the path `L` the distance to the point, at most the air column
/// seen at the point's zenith angle (`H / cos z`): so the ground is hazy
/// near the horizon from anywhere, barely from orbit straight down, and
/// the planet's limb glows. Computed in the fragment shader (shader.wgsl),
/// finite at every distance and inside the planet (heights below 0 count
/// as 0, a zero distance as no haze).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Atmosphere {
    /// Scale height `H` in metres.
    pub scale_height: f32,
    /// Visibility `V` at sea level in metres (optical depth 1).
    pub visibility: f32,
}

impl Atmosphere {
    /// The Earth's: 8 km scale height, 120 km visibility at sea level (clear air).
    pub const EARTH: Atmosphere = Atmosphere {
        scale_height: 8_000.0,
        visibility: 120_000.0,
    };

    /// The sky's colour at full density: the colour the aerial
    /// perspective fades terrain to (shader.wgsl `aerial`), lit by the
    /// sun's height `sun_up` (cosine of its zenith angle, clamped to 0..1).
    pub fn sky_colour(sun_up: f64) -> [f64; 3] {
        let k = 0.2 + 0.8 * sun_up.clamp(0.0, 1.0);
        [0.50 * k, 0.66 * k, 0.90 * k]
    }

    /// The background seen from `eye` (planet frame, metres): `space`
    /// above the air, the sky's colour ([`Atmosphere::sky_colour`] at the
    /// sun's height there) within it, mixed by the air's density at the
    /// eye's altitude above the ellipsoid of semi-axes `radii` (equatorial,
    /// polar; `exp(−h/H)`, 1 at and below the surface). `sun` is a unit
    /// vector. Finite for every eye: at the centre, or not finite, `space`.
    pub fn sky(&self, eye: [f64; 3], sun: [f64; 3], radii: [f64; 2], space: [f64; 4]) -> [f64; 4] {
        let eye = glam::DVec3::from(eye);
        let len = eye.length();
        if !(len.is_finite() && len > 0.0) {
            return space;
        }
        let d = eye / len;
        let (a, b) = (radii[0].max(1.0), radii[1].max(1.0));
        let r = 1.0 / ((d.x * d.x + d.y * d.y) / (a * a) + d.z * d.z / (b * b)).sqrt();
        let h = (len - r).max(0.0);
        let density = (-h / f64::from(self.scale_height.max(1.0))).exp();
        let sun_up = d.dot(glam::DVec3::from(sun));
        let sky = Self::sky_colour(if sun_up.is_finite() { sun_up } else { 0.0 });
        [
            space[0] + (sky[0] - space[0]) * density,
            space[1] + (sky[1] - space[1]) * density,
            space[2] + (sky[2] - space[2]) * density,
            space[3],
        ]
    }
}
