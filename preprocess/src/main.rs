//! `planet-build`: build, verify, inspect and sample planet databases
//! (thesis Chapter 5).

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};
use planet_core::Datum;
use planet_preprocess::{db, RasterOptions};
use std::path::PathBuf;

#[derive(Parser)]
#[command(
    name = "planet-build",
    version,
    about = "Build and check planet databases"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Build a database from rasters or a procedural planet.
    Build {
        /// Elevation rasters: GeoTIFFs in any geographic or projected CRS
        /// (EPSG code or user-defined GeoKeys; int16, uint16 or float32) or
        /// SRTM .hgt files. All must lie on one body.
        #[arg(long, num_args = 1..)]
        elevation: Vec<PathBuf>,
        /// Colour GeoTIFF (RGB8 or grey8), any CRS; alone, it builds a
        /// colour database on the datum's surface (zero heights).
        #[arg(long)]
        colour: Option<PathBuf>,
        /// Vertical datum of the elevation inputs' heights, converted to
        /// heights above the ellipsoid: egm96, egm2008 or ellipsoid; one
        /// for every input, or one per input in --elevation's order.
        /// Default: what each file declares, else EGM96 for int16
        /// geographic DEMs (said on stderr), else ellipsoid.
        #[arg(long, num_args = 1.., value_name = "egm96|egm2008|ellipsoid")]
        vertical_datum: Vec<planet_preprocess::geoid::VerticalDatum>,
        /// Build a procedural planet instead.
        #[arg(long, conflicts_with_all = ["elevation", "colour"])]
        procedural: bool,
        /// Procedural seed.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Procedural uniform leaf level (the base level).
        #[arg(long, default_value_t = 4)]
        levels: u8,
        /// Procedural detail region, repeatable: a circle of RADIUS_KM around
        /// LAT,LON (degrees) built down to leaf LEVEL (>= --levels, <= 20),
        /// graded outside it; colour follows the elevation to LEVEL inside
        /// the region and stays at --levels outside it.
        #[arg(
            long,
            value_name = "LAT,LON,RADIUS_KM,LEVEL",
            allow_hyphen_values = true
        )]
        detail: Vec<planet_preprocess::DetailRegion>,
        /// Sphere radius in metres (procedural; default WGS84).
        #[arg(long, conflicts_with = "wgs84")]
        radius: Option<f64>,
        /// WGS84 ellipsoid (the default).
        #[arg(long)]
        wgs84: bool,
        /// Procedural planet without colour.
        #[arg(long)]
        no_colour: bool,
        /// Output database.
        #[arg(long)]
        out: PathBuf,
        /// Deepest level (rasters).
        #[arg(long, default_value_t = 16)]
        max_level: u8,
        /// Memory bound in MiB (raster caches and in-flight grids).
        #[arg(long, default_value_t = 1024)]
        max_memory: usize,
        /// Print the process's peak resident set (VmHWM) after the build.
        #[arg(long)]
        report_memory: bool,
        /// Worker threads.
        #[arg(long)]
        threads: Option<usize>,
        /// No progress bars.
        #[arg(long)]
        quiet: bool,
    },
    /// Check every record of a database; exit 1 at the first bad offset.
    Verify {
        /// Database file.
        db: PathBuf,
    },
    /// Print header fields and per-level statistics.
    Inspect {
        /// Database file.
        db: PathBuf,
        /// JSON output.
        #[arg(long)]
        json: bool,
    },
    /// Height at a point: above the ellipsoid on the line before last, and
    /// alone on the last line in the sources' own vertical datum (the same
    /// for ellipsoidal or procedural databases).
    Sample {
        /// Database file.
        db: PathBuf,
        /// Latitude in degrees.
        #[arg(long, allow_negative_numbers = true)]
        lat: f64,
        /// Longitude in degrees.
        #[arg(long, allow_negative_numbers = true)]
        lon: f64,
    },
}

fn main() {
    planet_core::pipe::exit_quietly_on_broken_pipe();
    match run() {
        Ok(()) => {}
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::exit(1);
        }
    }
}

fn run() -> Result<()> {
    let cli = Cli::parse();
    match cli.cmd {
        Cmd::Build {
            elevation,
            colour,
            vertical_datum,
            procedural,
            seed,
            levels,
            detail,
            radius,
            wgs84: _,
            no_colour,
            out,
            max_level,
            max_memory,
            threads,
            quiet,
            report_memory,
        } => {
            if !procedural && !detail.is_empty() {
                bail!(
                    "--detail needs --procedural (raster trees follow their sources' resolution)"
                );
            }
            let stats = if procedural {
                let datum = match radius {
                    Some(r) => Datum::Sphere { radius: r },
                    None => Datum::WGS84,
                };
                if !datum.is_valid() {
                    bail!(
                        "invalid --radius {radius:?}: must be a finite number of metres in (0, {:e}]",
                        planet_core::datum::MAX_RADIUS
                    );
                }
                let opts = planet_preprocess::ProceduralOptions {
                    seed,
                    levels,
                    datum,
                    colour: !no_colour,
                    threads,
                    quiet,
                    max_memory_mb: Some(max_memory),
                    detail,
                };
                planet_preprocess::check_procedural_options(&opts)?;
                planet_preprocess::build_procedural(&opts, &out)
                    .with_context(|| format!("building {}", out.display()))?
            } else {
                if elevation.is_empty() && colour.is_none() {
                    bail!("give --elevation FILE..., --colour FILE or --procedural");
                }
                if vertical_datum.contains(&planet_preprocess::geoid::VerticalDatum::Egm2008) {
                    eprintln!(
                        "note: EGM2008 undulations come from the egm2008 crate's 3° grid \
                         (metre-level accuracy)"
                    );
                }
                let e: Vec<&std::path::Path> = elevation.iter().map(|p| p.as_path()).collect();
                planet_preprocess::build_rasters_noting(
                    &e,
                    colour.as_deref(),
                    &out,
                    &RasterOptions {
                        max_level,
                        max_memory_mb: max_memory,
                        threads,
                        quiet,
                        vertical: vertical_datum,
                    },
                    &mut |n| eprintln!("note: {n}"),
                )
                .with_context(|| format!("building {}", out.display()))?
            };
            println!(
                "wrote {}: {} bytes, {} elevation + {} colour records, max level {}/{}, {} samples in {:.2} s ({:.1} M samples/s)",
                out.display(),
                stats.file_bytes,
                stats.elevation_records,
                stats.colour_records,
                stats.max_level,
                stats.colour_max_level,
                stats.elevation_samples + stats.colour_samples,
                stats.seconds,
                stats.samples_per_second() / 1e6
            );
            if report_memory {
                // Linux only; absent elsewhere.
                let hwm = std::fs::read_to_string("/proc/self/status")
                    .ok()
                    .and_then(|s| {
                        s.lines()
                            .find(|l| l.starts_with("VmHWM:"))
                            .and_then(|l| l.split_whitespace().nth(1)?.parse::<u64>().ok())
                    });
                match hwm {
                    Some(kib) => println!("peak_rss_kib {kib}"),
                    None => println!("peak_rss_kib unknown"),
                }
            }
        }
        Cmd::Verify { db: path } => match db::verify(&path) {
            Ok(r) => println!(
                "OK: {} elevation records, {} colour records, max level {}",
                r.elevation_records, r.colour_records, r.max_level
            ),
            Err(e) => {
                println!("FAILED: {:#}", anyhow::Error::from(e));
                std::process::exit(1);
            }
        },
        Cmd::Inspect { db: path, json } => {
            let r = db::inspect(&path).with_context(|| format!("inspecting {}", path.display()))?;
            if json {
                println!("{}", serde_json::to_string_pretty(&r)?);
            } else {
                print_inspect(&r);
            }
        }
        Cmd::Sample { db: path, lat, lon } => {
            let s = db::Sampler::open(&path)?;
            let r = s.sample(lat, lon)?;
            println!("leaf {:?}", r.leaf);
            let v = s.vertical_datum();
            println!("ellipsoidal_height_m {}", r.metres);
            match v {
                Some(v) => {
                    println!("vertical_datum {v}");
                    println!("{}", s.in_vertical_datum(lat, lon, r.metres, v));
                }
                None => {
                    println!("vertical_datum ellipsoid");
                    println!("{}", r.metres);
                }
            }
        }
    }
    Ok(())
}

fn print_inspect(r: &db::InspectReport) {
    println!("file: {} bytes", r.file_bytes);
    println!("datum: {}", r.datum);
    println!(
        "elevation: scale {} m/unit, offset {} m, range {} .. {} m",
        r.elevation_scale, r.elevation_offset, r.min_elevation, r.max_elevation
    );
    println!("description: {}", r.description);
    let mut trees = vec![("elevation", &r.elevation)];
    if let Some(c) = &r.colour {
        trees.push(("colour", c));
    }
    for (name, t) in trees {
        println!(
            "{name} tree: width {}, max level {}, {} records, {} bytes, {} samples, raw {} bytes, ratio {:.1} %",
            t.block_width,
            t.max_level,
            t.records,
            t.bytes,
            t.samples,
            t.raw_bytes,
            100.0 * t.compression_ratio
        );
        for l in &t.levels {
            println!(
                "  level {:2}: {:8} records {:12} bytes  error max {:9.3} mean {:9.3}",
                l.level, l.records, l.bytes, l.max_error, l.mean_error
            );
        }
    }
}
