//! The built-in planet of `planet-view --local` (ISSUE #15): the procedural
//! planet of seed 1 at 4 levels (about 10 km between samples), deepened to
//! level 14 (about 9.6 m between samples on the Earth's datum) around three
//! named places, graded outside them (thesis §4.3.3). It builds in a few
//! seconds and stays small enough to be a first-use cache, while each place
//! streams visibly from orbit down to the ground.
//!
//! The places were chosen on this generator with
//! `cargo run --release -p planet-preprocess --example find_places -- DB`
//! (DB: `--procedural --seed 1 --levels 5`): the highest local relief, the
//! steepest coast (deep sea beside high land) and the deepest valley cut
//! into high ground, each on its own continent.

use crate::procedural::{default_procedural_options, DetailRegion, Procedural, ProceduralOptions};
use crate::GridSource;

/// A named place of the built-in planet.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Place {
    /// Short name (HUD, `G` key).
    pub name: &'static str,
    /// What the place is.
    pub what: &'static str,
    /// Latitude of the centre, degrees.
    pub lat: f64,
    /// Longitude of the centre, degrees.
    pub lon: f64,
}

/// The named places, in the order the viewer's `G` key visits them.
pub const PLACES: [Place; 3] = [
    Place {
        name: "Serra Alta",
        what: "mountain range, 5.6 km high",
        lat: -17.5,
        lon: -107.0,
    },
    Place {
        name: "Costa Brava",
        what: "steep coast: sea 1 km deep beside 2 km high land",
        lat: -5.0,
        lon: -97.75,
    },
    Place {
        name: "Vale Fundo",
        what: "valley 700 m below the high ground around it",
        lat: -8.25,
        lon: 132.75,
    },
];

/// Base leaf level of the built-in planet (about 10 km between samples).
pub const BASE_LEVELS: u8 = 4;
/// Leaf level inside the named places (about 9.6 m between samples).
pub const PLACE_LEVEL: u8 = 14;
/// Radius of each place's deepest region, kilometres.
pub const PLACE_RADIUS_KM: f64 = 12.0;

/// The options of the built-in planet (progress bars on).
pub fn builtin_options() -> ProceduralOptions {
    ProceduralOptions {
        levels: BASE_LEVELS,
        quiet: false,
        detail: PLACES
            .iter()
            .map(|p| DetailRegion {
                lat: p.lat,
                lon: p.lon,
                radius_km: PLACE_RADIUS_KM,
                level: PLACE_LEVEL,
            })
            .collect(),
        ..default_procedural_options()
    }
}

/// The header description a built-in database has: it names the generator
/// version and every option, so a cached file whose description differs was
/// made by another generator and is rebuilt.
pub fn builtin_description() -> String {
    Procedural::new(&builtin_options()).description()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::procedural::check_procedural_options;

    #[test]
    fn builtin_options_are_valid_and_deep() {
        let o = builtin_options();
        check_procedural_options(&o).expect("valid options");
        assert_eq!(o.detail.len(), PLACES.len());
        assert_eq!(Procedural::new(&o).plan().max_level(), PLACE_LEVEL);
        let d = builtin_description();
        assert!(
            d.contains(&format!(
                "generator {}",
                crate::procedural::GENERATOR_VERSION
            )),
            "{d}"
        );
        for p in PLACES {
            assert!(
                d.contains(&format!("{},{}", p.lat, p.lon)),
                "{d} lacks {}",
                p.name
            );
        }
    }
}
