//! `planet-build`: build, verify, inspect and sample planet databases
//! (thesis Chapter 5).

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};
use planet_core::Datum;
use planet_preprocess::{db, CodecOptions, ColourQuality, ElevationChoice, RasterOptions};
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
        /// SRTM .hgt files; a directory stands for every raster under it, a
        /// .txt or .list file for the rasters it lists (one per line). All
        /// must lie on one body; finer rasters win over coarser ones.
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
        /// Procedural seed (also the seed of --detail's noise on rasters).
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Procedural uniform leaf level (the base level).
        #[arg(long, default_value_t = 4)]
        levels: u8,
        /// Detail region, repeatable: a circle of RADIUS_KM around LAT,LON
        /// (degrees) built down to leaf LEVEL, graded outside it.
        /// Procedural: LEVEL >= --levels, <= 20; colour follows the
        /// elevation to LEVEL inside the region and stays at --levels
        /// outside it. Rasters: LEVEL deeper than the finest elevation
        /// source and <= --max-level; fractal detail beyond the sources,
        /// scaled by their local slope, is added inside the region (thesis
        /// §6.2.2); colour stays at its source's level.
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
        /// Largest elevation error in metres of any decoded sample (rounded
        /// down to whole stored units; 0: exact, the source's own
        /// quantisation).
        #[arg(long, default_value_t = 0.0)]
        max_error: f64,
        /// Elevation codec: `quantised` (quantised in the loop, rANS, codec
        /// id 3, honours --max-error; above 0 the tree is written exact
        /// beside the output first, then re-encoded), `quantised-2` (id 2's
        /// fixed grid) or `quantised-1` (id 1), for comparisons, or `legacy`
        /// (format v1's lossless lz4 byte planes, for comparisons).
        #[arg(long, default_value = "quantised", value_parser = ["quantised", "quantised-2", "quantised-1", "legacy"])]
        elevation_codec: String,
        /// Colour quality: a PSNR in dB against the source (Haar details,
        /// zstd), `lossless` (PTM deltas, zstd) or `lossless-legacy` (format
        /// v1's PTM deltas, lz4).
        #[arg(long, default_value = "42")]
        colour_quality: ColourQuality,
    },
    /// Check every record of a database; exit 1 at the first bad offset.
    /// With the source it was built from (the same source options as
    /// `build`), also check every decoded elevation sample against the
    /// source within the codec's max error and report the colour PSNR.
    Verify {
        /// Database file.
        db: PathBuf,
        /// Elevation GeoTIFFs the database was built from.
        #[arg(long, num_args = 1..)]
        elevation: Vec<PathBuf>,
        /// Colour GeoTIFF the database was built from.
        #[arg(long)]
        colour: Option<PathBuf>,
        /// The database is a procedural planet (give its --seed, --levels
        /// and --detail).
        #[arg(long, conflicts_with_all = ["elevation", "colour"])]
        procedural: bool,
        /// Procedural seed (also the seed of --detail's noise on rasters).
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Procedural uniform leaf level.
        #[arg(long, default_value_t = 4)]
        levels: u8,
        /// Detail regions the database was built with (procedural or
        /// rasters).
        #[arg(
            long,
            value_name = "LAT,LON,RADIUS_KM,LEVEL",
            allow_hyphen_values = true
        )]
        detail: Vec<planet_preprocess::DetailRegion>,
        /// Deepest level (rasters).
        #[arg(long, default_value_t = 16)]
        max_level: u8,
        /// JSON output.
        #[arg(long)]
        json: bool,
    },
    /// Print header fields and per-level statistics.
    Inspect {
        /// Database file.
        db: PathBuf,
        /// JSON output.
        #[arg(long)]
        json: bool,
    },
    /// Re-project and sample every elevation leaf grid a build from these
    /// rasters would make, and nothing else (no LODs, encoding or file):
    /// the re-projection part of a build, timed alone.
    Resample {
        /// Elevation rasters (as `build`).
        #[arg(long, num_args = 1.., required = true)]
        elevation: Vec<PathBuf>,
        /// Vertical datum of the inputs (as `build`).
        #[arg(long, num_args = 1.., value_name = "egm96|egm2008|ellipsoid")]
        vertical_datum: Vec<planet_preprocess::geoid::VerticalDatum>,
        /// Deepest level.
        #[arg(long, default_value_t = 16)]
        max_level: u8,
        /// Memory bound in MiB (raster caches).
        #[arg(long, default_value_t = 1024)]
        max_memory: usize,
        /// Worker threads.
        #[arg(long)]
        threads: Option<usize>,
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
            max_error,
            elevation_codec,
            colour_quality,
        } => {
            let codecs = CodecOptions {
                elevation: if elevation_codec == "legacy" {
                    if max_error != 0.0 {
                        bail!("--max-error needs --elevation-codec quantised");
                    }
                    ElevationChoice::Legacy
                } else if elevation_codec == "quantised-1" {
                    ElevationChoice::MaxErrorId1(max_error)
                } else if elevation_codec == "quantised-2" {
                    ElevationChoice::MaxErrorId2(max_error)
                } else {
                    ElevationChoice::MaxError(max_error)
                },
                colour: colour_quality,
            };
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
                    codecs,
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
                let elevation = planet_preprocess::inputs::expand(&elevation)?;
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
                        codecs,
                        detail,
                        seed,
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
        Cmd::Resample {
            elevation,
            vertical_datum,
            max_level,
            max_memory,
            threads,
        } => {
            let elevation = planet_preprocess::inputs::expand(&elevation)?;
            let e: Vec<&std::path::Path> = elevation.iter().map(|p| p.as_path()).collect();
            let st = planet_preprocess::resample_rasters(
                &e,
                &RasterOptions {
                    max_level,
                    max_memory_mb: max_memory,
                    threads,
                    vertical: vertical_datum,
                    ..RasterOptions::default()
                },
            )?;
            println!(
                "resampled {} leaf grids, {} samples in {:.2} s ({:.1} M samples/s, checksum {})",
                st.leaves,
                st.samples,
                st.seconds,
                st.samples as f64 / st.seconds.max(1e-9) / 1e6,
                st.checksum
            );
        }
        Cmd::Verify {
            db: path,
            elevation,
            colour,
            procedural,
            seed,
            levels,
            detail,
            max_level,
            json,
        } => {
            let result = if procedural {
                let opts = planet_preprocess::ProceduralOptions {
                    seed,
                    levels,
                    detail,
                    ..planet_preprocess::default_procedural_options()
                };
                planet_preprocess::check_procedural_options(&opts)?;
                let src = planet_preprocess::Procedural::new(&opts);
                db::verify_against(&path, Some(&src))
            } else if !elevation.is_empty() {
                let elevation = planet_preprocess::inputs::expand(&elevation)?;
                let e: Vec<&std::path::Path> = elevation.iter().map(|p| p.as_path()).collect();
                let (src, _) = planet_preprocess::open_rasters(
                    &e,
                    colour.as_deref(),
                    &RasterOptions {
                        max_level,
                        detail,
                        seed,
                        ..RasterOptions::default()
                    },
                )?;
                db::verify_against(&path, Some(&src))
            } else {
                db::verify(&path)
            };
            match result {
                Ok(r) if json => println!("{}", serde_json::to_string_pretty(&r)?),
                Ok(r) => {
                    println!(
                        "OK: {} elevation records, {} colour records, max level {}",
                        r.elevation_records, r.colour_records, r.max_level
                    );
                    if let (Some(b), Some(e)) = (r.elevation_bound_m, r.elevation_max_error_m) {
                        println!("elevation error against the source: max {e} m (bound {b} m)");
                    }
                    if let (Some(p), Some(m)) = (r.colour_psnr, r.colour_min_record_psnr) {
                        println!(
                            "colour PSNR against the source: {p:.2} dB (lowest record {m:.2} dB)"
                        );
                    }
                }
                Err(e) => {
                    println!("FAILED: {:#}", anyhow::Error::from(e));
                    std::process::exit(1);
                }
            }
        }
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
        let params: Vec<String> = t
            .codec_params
            .iter()
            .map(|(k, v)| format!("{k} {v}"))
            .collect();
        println!(
            "  codec {} (id {}) {}",
            t.codec,
            t.codec_id,
            params.join(", ")
        );
        for l in &t.levels {
            println!(
                "  level {:2}: {:8} records {:12} bytes  error max {:9.3} mean {:9.3}",
                l.level, l.records, l.bytes, l.max_error, l.mean_error
            );
        }
    }
}
