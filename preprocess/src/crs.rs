//! Coordinate reference systems of raster inputs: the GeoTIFF GeoKeys (OGC
//! GeoTIFF 1.1, §7; the key and code values of its Annex) turned into a PROJ
//! definition string, and the per-sample inverse mapping of thesis §5.2
//! (output latitude/longitude → source CRS → pixel) done by `proj4rs`.
//!
//! No projection formula is written here: an EPSG code is looked up in the
//! `crs-definitions` table (the EPSG registry's PROJ strings), a user-defined
//! CRS (code 32767) is assembled into a PROJ string from its GeoKeys, and
//! `proj4rs` (a Rust port of PROJ's projections) projects.
//!
//! The surface the samples are placed on (the database's datum) follows the
//! CRS's ellipsoid: any Earth ellipsoid (WGS84, GRS80, Clarke, Bessel, …, see
//! [`planet_core::datum::Body`]) means WGS84, with the CRS's datum shift
//! (`+towgs84`, as PROJ 4 does: NAD83 and ETRS89 are 0 shifts; NAD27 needs
//! grids that are not shipped and is refused); any other ellipsoid or sphere
//! is another body's, and the samples stay on it (latitude/longitude on the
//! body, no shift).

use planet_core::datum::Body;
use planet_core::Datum;
use proj4rs::proj::Proj;
use std::collections::HashMap;

/// GeoKey ids (GeoTIFF 1.1 Annex).
mod key {
    pub const GT_MODEL_TYPE: u16 = 1024;
    pub const GT_RASTER_TYPE: u16 = 1025;
    pub const GEOGRAPHIC_TYPE: u16 = 2048;
    pub const GEOG_GEODETIC_DATUM: u16 = 2050;
    pub const GEOG_ANGULAR_UNITS: u16 = 2054;
    pub const GEOG_ELLIPSOID: u16 = 2056;
    pub const GEOG_SEMI_MAJOR_AXIS: u16 = 2057;
    pub const GEOG_SEMI_MINOR_AXIS: u16 = 2058;
    pub const GEOG_INV_FLATTENING: u16 = 2059;
    pub const PROJECTED_CS_TYPE: u16 = 3072;
    pub const PROJECTION: u16 = 3074;
    pub const PROJ_COORD_TRANS: u16 = 3075;
    pub const PROJ_LINEAR_UNITS: u16 = 3076;
    pub const PROJ_STD_PARALLEL1: u16 = 3078;
    pub const PROJ_STD_PARALLEL2: u16 = 3079;
    pub const PROJ_NAT_ORIGIN_LONG: u16 = 3080;
    pub const PROJ_NAT_ORIGIN_LAT: u16 = 3081;
    pub const PROJ_FALSE_EASTING: u16 = 3082;
    pub const PROJ_FALSE_NORTHING: u16 = 3083;
    pub const PROJ_FALSE_ORIGIN_LONG: u16 = 3084;
    pub const PROJ_FALSE_ORIGIN_LAT: u16 = 3085;
    pub const PROJ_FALSE_ORIGIN_EASTING: u16 = 3086;
    pub const PROJ_FALSE_ORIGIN_NORTHING: u16 = 3087;
    pub const PROJ_CENTER_LONG: u16 = 3088;
    pub const PROJ_CENTER_LAT: u16 = 3089;
    pub const PROJ_SCALE_AT_NAT_ORIGIN: u16 = 3092;
    pub const PROJ_SCALE_AT_CENTER: u16 = 3093;
    pub const PROJ_STRAIGHT_VERT_POLE_LONG: u16 = 3095;
    pub const VERTICAL_CS_TYPE: u16 = 4096;
    pub const VERTICAL_DATUM: u16 = 4098;
}

/// "User-defined" in every GeoKey code space.
pub const USER_DEFINED: u16 = 32767;

/// The parsed GeoKeyDirectory (tag 34735) with its double (34736) and ASCII
/// (34737) parameters.
#[derive(Debug, Clone, Default)]
pub struct GeoKeys {
    shorts: HashMap<u16, u16>,
    doubles: HashMap<u16, f64>,
}

impl GeoKeys {
    /// Parse a key directory; keys whose values lie outside the parameter
    /// tags are ignored (a malformed file then fails on a missing key).
    pub fn parse(dir: &[u16], doubles: &[f64]) -> GeoKeys {
        let mut k = GeoKeys::default();
        let n = dir.get(3).copied().unwrap_or(0) as usize;
        for i in 0..n {
            let Some(e) = dir.get(4 + 4 * i..8 + 4 * i) else {
                break;
            };
            let (id, loc, count, val) = (e[0], e[1], e[2], e[3]);
            match loc {
                0 => {
                    k.shorts.insert(id, val);
                }
                34736 if count >= 1 => {
                    if let Some(&d) = doubles.get(val as usize) {
                        k.doubles.insert(id, d);
                    }
                }
                _ => {}
            }
        }
        k
    }

    /// A SHORT key.
    pub fn short(&self, id: u16) -> Option<u16> {
        self.shorts.get(&id).copied()
    }

    /// A DOUBLE key.
    pub fn double(&self, id: u16) -> Option<f64> {
        self.doubles.get(&id).copied()
    }

    /// Whether the raster is pixel-is-point (GTRasterType 2).
    pub fn pixel_is_point(&self) -> bool {
        self.short(key::GT_RASTER_TYPE) == Some(2)
    }

    /// The vertical datum the keys declare, if one this builder knows.
    pub fn vertical(&self) -> Option<crate::geoid::VerticalDatum> {
        use crate::geoid::VerticalDatum as V;
        match (
            self.short(key::VERTICAL_CS_TYPE),
            self.short(key::VERTICAL_DATUM),
        ) {
            (Some(5773), _) | (_, Some(5171)) => Some(V::Egm96),
            (Some(3855), _) | (_, Some(1027)) => Some(V::Egm2008),
            // Ellipsoidal heights (the vertical part of EPSG:4979 and kin).
            (Some(5030), _) | (Some(4979), _) => Some(V::Ellipsoid),
            _ => None,
        }
    }
}

/// Why a CRS cannot be used.
pub type CrsError = String;

/// A raster's CRS and the mapping between its coordinates and the latitude
/// and longitude of the database's surface.
pub struct Crs {
    /// The PROJ definition used (`+proj=longlat +datum=WGS84` for EPSG:4326).
    pub definition: String,
    /// Short human name: `EPSG:32610`, or `user-defined lcc`.
    pub name: String,
    /// Whether raster coordinates are longitude/latitude in degrees (else
    /// projected, in the CRS's linear unit).
    pub geographic: bool,
    /// The surface the samples are placed on.
    pub datum: Datum,
    /// `None`: raster coordinates are the surface's longitude/latitude.
    transform: Option<Transform>,
}

struct Transform {
    /// The raster's CRS.
    src: Proj,
    /// Longitude/latitude on the surface (WGS84 for Earth CRSs).
    dst: Proj,
}

impl std::fmt::Debug for Crs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} ({})", self.name, self.definition)
    }
}

/// PROJ string of an ellipsoid given by its axes.
fn ellps_params(a: f64, b: f64) -> String {
    format!("+a={a} +b={b}")
}

/// Semi-axes of the EPSG ellipsoids GeoTIFFs name by code.
fn ellipsoid_by_code(code: u16) -> Option<(f64, f64)> {
    let inv = |a: f64, rf: f64| (a, a * (1.0 - 1.0 / rf));
    Some(match code {
        7030 => inv(6_378_137.0, 298.257_223_563), // WGS 84
        7019 => inv(6_378_137.0, 298.257_222_101), // GRS 1980
        7043 => inv(6_378_135.0, 298.26),          // WGS 72
        7022 => inv(6_378_388.0, 297.0),           // International 1924
        7004 => inv(6_377_397.155, 299.152_812_8), // Bessel 1841
        7008 => (6_378_206.4, 6_356_583.8),        // Clarke 1866
        7001 => inv(6_377_563.396, 299.324_964_6), // Airy 1830
        7024 => inv(6_378_245.0, 298.3),           // Krassowsky 1940
        7035 | 7047 => (6_371_000.0, 6_371_000.0), // GRS80 authalic sphere
        7059 => (6_378_137.0, 6_378_137.0),        // Popular Visualisation Sphere
        _ => return None,
    })
}

/// Semi-axes in a PROJ string (`+a`/`+b`/`+rf`/`+R`, `+ellps`, `+datum`).
fn axes_of(def: &str) -> Option<(f64, f64)> {
    let mut a = None;
    let mut b = None;
    let mut rf = None;
    let mut named = None;
    for tok in def.split_whitespace() {
        let tok = tok.trim_start_matches('+');
        let (k, v) = tok.split_once('=').unwrap_or((tok, ""));
        match k {
            "a" | "R" => a = v.parse::<f64>().ok(),
            "b" => b = v.parse::<f64>().ok(),
            "rf" => rf = v.parse::<f64>().ok(),
            "ellps" | "datum" => {
                named = match v {
                    "WGS84" => ellipsoid_by_code(7030),
                    "GRS80" | "NAD83" => ellipsoid_by_code(7019),
                    "WGS72" => ellipsoid_by_code(7043),
                    "intl" => ellipsoid_by_code(7022),
                    "bessel" | "potsdam" => ellipsoid_by_code(7004),
                    "clrk66" | "NAD27" => ellipsoid_by_code(7008),
                    "airy" | "OSGB36" => ellipsoid_by_code(7001),
                    "krass" => ellipsoid_by_code(7024),
                    _ => Some((6_378_137.0, 6_356_752.314_245)), // an Earth ellipsoid
                }
                .or(named)
            }
            _ => {}
        }
    }
    match (a, b, rf) {
        (Some(a), Some(b), _) => Some((a, b)),
        (Some(a), None, Some(rf)) if rf != 0.0 => Some((a, a * (1.0 - 1.0 / rf))),
        (Some(a), None, _) => Some((a, a)),
        _ => named,
    }
}

const WGS84_LONGLAT: &str = "+proj=longlat +datum=WGS84 +no_defs";

impl Crs {
    /// EPSG:4326, the identity.
    pub fn wgs84() -> Crs {
        Crs {
            definition: WGS84_LONGLAT.into(),
            name: "EPSG:4326".into(),
            geographic: true,
            datum: Datum::WGS84,
            transform: None,
        }
    }

    /// A CRS from its PROJ definition.
    pub fn from_definition(definition: &str, name: String) -> Result<Crs, CrsError> {
        let src = Proj::from_proj_string(definition)
            .map_err(|e| format!("{name}: PROJ cannot use `{definition}`: {e}"))?;
        let geographic = src.is_latlong();
        let (a, b) =
            axes_of(definition).ok_or_else(|| format!("{name}: no ellipsoid in `{definition}`"))?;
        let body = Body::of_axes(a, b);
        if !geographic && !src.has_inverse() {
            return Err(format!("{name}: the projection has no inverse"));
        }
        let (datum, dst_def) = if body == Some(Body::Earth) {
            (Datum::WGS84, WGS84_LONGLAT.to_string())
        } else {
            (
                Datum::from_axes(a, b),
                format!("+proj=longlat {} +no_defs", ellps_params(a, b)),
            )
        };
        if !datum.is_valid() {
            return Err(format!("{name}: invalid ellipsoid a = {a} m, b = {b} m"));
        }
        // No transform where the raster is already longitude/latitude on
        // the surface: EPSG:4326, or a geographic CRS of another body.
        let identity = geographic
            && (body != Some(Body::Earth)
                || definition.contains("+datum=WGS84")
                || (datum_is_wgs84_axes(a, b) && !definition.contains("towgs84")));
        let transform = if identity {
            None
        } else {
            let dst = Proj::from_proj_string(&dst_def)
                .map_err(|e| format!("{name}: PROJ cannot use `{dst_def}`: {e}"))?;
            Some(Transform { src, dst })
        };
        let crs = Crs {
            definition: definition.into(),
            name,
            geographic,
            datum,
            transform,
        };
        // Fail now, naming the CRS, if PROJ cannot shift its datum (NAD27
        // and others that need grids).
        if let Some(t) = &crs.transform {
            let mut p = (0.0, 0.0, 0.0);
            if let Err(e) = proj4rs::transform::transform(&t.src, &t.dst, &mut p) {
                if matches!(
                    e,
                    proj4rs::errors::Error::NadGridNotAvailable
                        | proj4rs::errors::Error::InvalidDatum
                ) {
                    return Err(format!("{}: datum shift not available: {e}", crs.name));
                }
            }
        }
        Ok(crs)
    }

    /// A CRS by EPSG code (geographic or projected).
    pub fn from_epsg(code: u16) -> Result<Crs, CrsError> {
        let def =
            crs_definitions::from_code(code).ok_or_else(|| format!("unknown EPSG code {code}"))?;
        if code == 4326 {
            return Ok(Crs::wgs84());
        }
        Crs::from_definition(def.proj4, format!("EPSG:{code}"))
    }

    /// The CRS of a GeoTIFF's keys.
    pub fn from_geokeys(k: &GeoKeys) -> Result<Crs, CrsError> {
        let model = k.short(key::GT_MODEL_TYPE);
        match model {
            None | Some(2) => Crs::geographic_from_keys(k),
            Some(1) => match k.short(key::PROJECTED_CS_TYPE) {
                Some(USER_DEFINED) | None => Crs::projected_from_keys(k),
                Some(code) => {
                    Crs::from_epsg(code).map_err(|e| format!("ProjectedCSType {code}: {e}"))
                }
            },
            Some(m) => Err(format!(
                "GTModelType {m} (1 projected and 2 geographic are read)"
            )),
        }
    }

    /// The geographic part of the keys as PROJ parameters (`+datum=…`,
    /// `+ellps=…` or `+a +b`, with `+towgs84` for Earth datums), and the
    /// name.
    fn geog_params(k: &GeoKeys) -> Result<(String, String), CrsError> {
        if let Some(code) = k.short(key::GEOGRAPHIC_TYPE).filter(|&c| c != USER_DEFINED) {
            let def = crs_definitions::from_code(code)
                .ok_or_else(|| format!("GeographicType {code}: unknown EPSG code"))?;
            let params: Vec<&str> = def
                .proj4
                .split_whitespace()
                .filter(|t| !t.starts_with("+proj=") && *t != "+no_defs")
                .collect();
            return Ok((params.join(" "), format!("EPSG:{code}")));
        }
        // User-defined: the datum by code, else the ellipsoid by code or axes.
        match k.short(key::GEOG_GEODETIC_DATUM) {
            Some(6326) => return Ok(("+datum=WGS84".into(), "WGS 84 datum".into())),
            Some(6269) => return Ok(("+datum=NAD83".into(), "NAD83 datum".into())),
            Some(6258) => {
                return Ok((
                    "+ellps=GRS80 +towgs84=0,0,0,0,0,0,0".into(),
                    "ETRS89 datum".into(),
                ))
            }
            _ => {}
        }
        let (a, b) = match k.short(key::GEOG_ELLIPSOID).filter(|&c| c != USER_DEFINED) {
            Some(code) => ellipsoid_by_code(code)
                .ok_or_else(|| format!("GeogEllipsoid {code}: unknown ellipsoid code"))?,
            None => {
                let a = k.double(key::GEOG_SEMI_MAJOR_AXIS).ok_or_else(|| {
                    "user-defined geographic CRS without GeogSemiMajorAxis".to_string()
                })?;
                let b = match (
                    k.double(key::GEOG_SEMI_MINOR_AXIS),
                    k.double(key::GEOG_INV_FLATTENING),
                ) {
                    (Some(b), _) => b,
                    (None, Some(rf)) if rf != 0.0 => a * (1.0 - 1.0 / rf),
                    _ => a,
                };
                (a, b)
            }
        };
        if !(a.is_finite() && b.is_finite() && a > 0.0 && b > 0.0 && b <= a) {
            return Err(format!("invalid ellipsoid a = {a} m, b = {b} m"));
        }
        let shift = if Body::of_axes(a, b) == Some(Body::Earth) {
            // An Earth datum with no known shift: as PROJ's "ballpark"
            // transformation, none.
            " +towgs84=0,0,0,0,0,0,0"
        } else {
            ""
        };
        Ok((
            format!("{}{shift}", ellps_params(a, b)),
            format!("user-defined ellipsoid a = {a} m, b = {b} m"),
        ))
    }

    fn geographic_from_keys(k: &GeoKeys) -> Result<Crs, CrsError> {
        if let Some(u) = k.short(key::GEOG_ANGULAR_UNITS) {
            if u != 9102 && u != 9122 {
                return Err(format!("GeogAngularUnits {u} (degrees, 9102, are read)"));
            }
        }
        match k.short(key::GEOGRAPHIC_TYPE) {
            None | Some(4326) => Ok(Crs::wgs84()),
            _ => {
                let (params, name) = Crs::geog_params(k)?;
                Crs::from_definition(&format!("+proj=longlat {params} +no_defs"), name)
            }
        }
    }

    fn projected_from_keys(k: &GeoKeys) -> Result<Crs, CrsError> {
        let ct = k
            .short(key::PROJ_COORD_TRANS)
            .ok_or("user-defined projected CRS without ProjCoordTrans")?;
        let d = |id: u16| k.double(id);
        let first = |ids: &[u16]| ids.iter().find_map(|&i| d(i));
        let nat_lat = first(&[
            key::PROJ_NAT_ORIGIN_LAT,
            key::PROJ_FALSE_ORIGIN_LAT,
            key::PROJ_CENTER_LAT,
        ])
        .unwrap_or(0.0);
        let nat_lon = first(&[
            key::PROJ_NAT_ORIGIN_LONG,
            key::PROJ_FALSE_ORIGIN_LONG,
            key::PROJ_CENTER_LONG,
            key::PROJ_STRAIGHT_VERT_POLE_LONG,
        ])
        .unwrap_or(0.0);
        let x0 = first(&[key::PROJ_FALSE_EASTING, key::PROJ_FALSE_ORIGIN_EASTING]).unwrap_or(0.0);
        let y0 = first(&[key::PROJ_FALSE_NORTHING, key::PROJ_FALSE_ORIGIN_NORTHING]).unwrap_or(0.0);
        let kk = first(&[key::PROJ_SCALE_AT_NAT_ORIGIN, key::PROJ_SCALE_AT_CENTER]).unwrap_or(1.0);
        let sp1 = d(key::PROJ_STD_PARALLEL1);
        let sp2 = d(key::PROJ_STD_PARALLEL2);
        let need = |v: Option<f64>, what: &str| {
            v.ok_or_else(|| format!("user-defined projection {ct} without {what}"))
        };
        // Coordinate transformation codes of GeoTIFF 1.1 Annex C.
        let proj = match ct {
            1 => format!("+proj=tmerc +lat_0={nat_lat} +lon_0={nat_lon} +k={kk}"),
            7 => match sp1 {
                Some(ts) => format!("+proj=merc +lat_ts={ts} +lon_0={nat_lon}"),
                None => format!("+proj=merc +lon_0={nat_lon} +k={kk}"),
            },
            8 => format!(
                "+proj=lcc +lat_1={} +lat_2={} +lat_0={nat_lat} +lon_0={nat_lon}",
                need(sp1, "ProjStdParallel1")?,
                need(sp2, "ProjStdParallel2")?
            ),
            9 => format!("+proj=lcc +lat_1={nat_lat} +lat_0={nat_lat} +lon_0={nat_lon} +k_0={kk}"),
            10 => format!("+proj=laea +lat_0={nat_lat} +lon_0={nat_lon}"),
            11 => format!(
                "+proj=aea +lat_1={} +lat_2={} +lat_0={nat_lat} +lon_0={nat_lon}",
                need(sp1, "ProjStdParallel1")?,
                need(sp2, "ProjStdParallel2")?
            ),
            14 => format!("+proj=stere +lat_0={nat_lat} +lon_0={nat_lon} +k={kk}"),
            15 => {
                // Polar stereographic: the natural-origin latitude is the
                // latitude of true scale (variant B) or the pole (variant A,
                // with a scale factor).
                let pole = if nat_lat < 0.0 { -90.0 } else { 90.0 };
                if nat_lat.abs() == 90.0 {
                    format!("+proj=stere +lat_0={pole} +lon_0={nat_lon} +k={kk}")
                } else {
                    format!("+proj=stere +lat_0={pole} +lat_ts={nat_lat} +lon_0={nat_lon}")
                }
            }
            16 => format!("+proj=sterea +lat_0={nat_lat} +lon_0={nat_lon} +k={kk}"),
            17 => format!(
                "+proj=eqc +lat_ts={} +lon_0={nat_lon}",
                sp1.unwrap_or(nat_lat)
            ),
            other => {
                return Err(format!(
                    "user-defined projection with ProjCoordTrans {other} (not read)"
                ))
            }
        };
        let units = match k.short(key::PROJ_LINEAR_UNITS) {
            None | Some(9001) => "+units=m",
            Some(9002) => "+units=ft",
            Some(9003) => "+units=us-ft",
            Some(u) => return Err(format!("ProjLinearUnits {u} (metres or feet are read)")),
        };
        let (geog, gname) = Crs::geog_params(k)?;
        let def = format!("{proj} +x_0={x0} +y_0={y0} {geog} {units} +no_defs");
        let name = format!(
            "user-defined {} on {gname}",
            proj.split_whitespace()
                .next()
                .unwrap_or("")
                .trim_start_matches("+proj=")
        );
        let _ = key::PROJECTION;
        Crs::from_definition(&def, name)
    }

    /// Raster CRS coordinates `(x, y)` of a surface point (degrees); for a
    /// geographic CRS `(lon, lat)` in degrees. `None` outside the
    /// projection's domain.
    #[inline]
    pub fn forward(&self, lat: f64, lon: f64) -> Option<(f64, f64)> {
        match &self.transform {
            None => Some((lon, lat)),
            Some(t) => {
                let mut p = (lon.to_radians(), lat.to_radians(), 0.0);
                proj4rs::transform::transform(&t.dst, &t.src, &mut p).ok()?;
                let (x, y) = if self.geographic {
                    (p.0.to_degrees(), p.1.to_degrees())
                } else {
                    (p.0, p.1)
                };
                (x.is_finite() && y.is_finite()).then_some((x, y))
            }
        }
    }

    /// The surface point `(lat, lon)` (degrees) of raster CRS coordinates.
    #[inline]
    pub fn inverse(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        match &self.transform {
            None => Some((y, x)),
            Some(t) => {
                let mut p = if self.geographic {
                    (x.to_radians(), y.to_radians(), 0.0)
                } else {
                    (x, y, 0.0)
                };
                proj4rs::transform::transform(&t.src, &t.dst, &mut p).ok()?;
                let (lat, lon) = (p.1.to_degrees(), p.0.to_degrees());
                (lat.is_finite() && lon.is_finite() && lat.abs() <= 90.0).then_some((lat, lon))
            }
        }
    }

    /// Whether raster coordinates are the surface's longitude/latitude.
    pub fn is_identity(&self) -> bool {
        self.transform.is_none()
    }
}

fn datum_is_wgs84_axes(a: f64, b: f64) -> bool {
    (a - 6_378_137.0).abs() < 1e-3 && (b - Datum::WGS84.polar_radius()).abs() < 1e-3
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn utm_round_trip_against_known_point() {
        // EPSG:32610 of (46.85 N, 121.76 W), as PROJ's cs2cs prints it.
        let c = Crs::from_epsg(32610).unwrap();
        let (x, y) = c.forward(46.85, -121.76).unwrap();
        assert!(
            (x - 594_534.76).abs() < 0.01 && (y - 5_189_241.75).abs() < 0.01,
            "{x} {y}"
        );
        let (la, lo) = c.inverse(x, y).unwrap();
        assert!((la - 46.85).abs() < 1e-9 && (lo + 121.76).abs() < 1e-9);
        assert_eq!(c.datum, Datum::WGS84);
    }

    #[test]
    fn bodies_from_axes() {
        let moon = Crs::from_definition("+proj=longlat +a=1737400 +b=1737400 +no_defs", "m".into())
            .unwrap();
        assert_eq!(
            moon.datum,
            Datum::Sphere {
                radius: 1_737_400.0
            }
        );
        assert!(moon.is_identity());
        let nad83 = Crs::from_epsg(4269).unwrap();
        assert_eq!(nad83.datum, Datum::WGS84);
        let (x, y) = nad83.forward(10.0, 20.0).unwrap();
        assert!((x - 20.0).abs() < 1e-9 && (y - 10.0).abs() < 1e-9);
        assert!(Crs::from_epsg(4267).is_err(), "NAD27 needs grids");
        assert!(Crs::from_epsg(1).is_err());
    }
}
