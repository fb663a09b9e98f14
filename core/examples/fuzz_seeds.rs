//! Writes valid records and headers as seeds for the fuzz corpora:
//! `cargo run -p planet-core --example fuzz_seeds -- fuzz/corpus`.
use planet_core::codec::{colour::HaarParams, ColourCodec, ElevationCodec};
use planet_core::format::{encode_record, ChildRef, Header, Tree, TreeInfo};
use planet_core::lod::colour_filter;
use planet_core::{BlockId, Datum, Face};
use std::path::PathBuf;

fn main() -> std::io::Result<()> {
    let dir = PathBuf::from(
        std::env::args()
            .nth(1)
            .unwrap_or_else(|| "fuzz/corpus".into()),
    );
    let rec_dir = dir.join("db_record");
    let hdr_dir = dir.join("db_header");
    std::fs::create_dir_all(&rec_dir)?;
    std::fs::create_dir_all(&hdr_dir)?;
    let block = BlockId::new(Face::new(2).unwrap(), 3, 5, 1).unwrap();
    let kid = ChildRef {
        offset: 64,
        size: 200,
        error: 2.5,
        min_elevation: -5.0,
        max_elevation: 80.0,
    };
    let w = 64;
    let grid: Vec<i16> = (0..(w + 1) * (w + 1))
        .map(|k| ((k * 37) % 500) as i16 - 100)
        .collect();
    let elev = encode_record(
        Tree::Elevation,
        block,
        &[kid; 4],
        &ElevationCodec::Legacy.encode(&grid, w),
    );
    std::fs::write(rec_dir.join("seed-elevation"), elev)?;
    let leaf = encode_record(
        Tree::Elevation,
        block,
        &[],
        &ElevationCodec::Legacy.encode(&grid, w),
    );
    std::fs::write(rec_dir.join("seed-elevation-leaf"), leaf)?;
    for k in [0u16, 3] {
        for (name, c) in [
            ("quantised", ElevationCodec::Quantised { max_error: k }),
            ("laplace", ElevationCodec::Laplace { max_error: k }),
            ("in-loop", ElevationCodec::InLoop { max_error: k }),
        ] {
            let rec = encode_record(Tree::Elevation, block, &[], &c.encode(&grid, w));
            std::fs::write(rec_dir.join(format!("seed-elevation-{name}-{k}")), rec)?;
        }
    }
    let cw = 128;
    let full: Vec<[u8; 3]> = (0..cw * cw)
        .map(|k| [(k % 251) as u8, (k % 13) as u8, 200])
        .collect();
    let lod1 = colour_filter(&full, cw);
    for (name, c) in [
        ("seed-colour", ColourCodec::Legacy),
        ("seed-colour-lossless", ColourCodec::Lossless),
        (
            "seed-colour-haar",
            ColourCodec::Haar(HaarParams::for_psnr(42.0)),
        ),
    ] {
        let rec = encode_record(Tree::Colour, block, &[], &c.encode(&full, &lod1, cw, 1).0);
        std::fs::write(rec_dir.join(name), rec)?;
    }
    let eh = (w / 2 + 1) * (w / 2 + 1);
    for (with_colour, codec) in [
        (false, ElevationCodec::Quantised { max_error: 1 }),
        (true, ElevationCodec::Quantised { max_error: 1 }),
        (true, ElevationCodec::Laplace { max_error: 1 }),
        (true, ElevationCodec::InLoop { max_error: 1 }),
    ] {
        let h = Header {
            datum: Datum::WGS84,
            elevation_scale: 1.0,
            elevation_offset: 0.0,
            min_elevation: -100.0,
            max_elevation: 400.0,
            elevation: TreeInfo {
                block_width: w as u16,
                codec,
                max_level: 3,
                root_records: [kid; 6],
                root_first_lods: std::array::from_fn(|_| vec![7i16; eh]),
            },
            colour: with_colour.then(|| TreeInfo {
                block_width: cw as u16,
                codec: ColourCodec::Haar(HaarParams::for_psnr(42.0)),
                max_level: 2,
                root_records: [kid; 6],
                root_first_lods: std::array::from_fn(|_| vec![[1u8, 2, 3]; (cw / 2) * (cw / 2)]),
            }),
            description: "fuzz seed".into(),
        };
        std::fs::write(
            hdr_dir.join(match codec {
                ElevationCodec::Laplace { .. } => format!("seed-header-{with_colour}-laplace"),
                ElevationCodec::InLoop { .. } => format!("seed-header-{with_colour}-in-loop"),
                _ => format!("seed-header-{with_colour}"),
            }),
            h.encode(),
        )?;
    }
    Ok(())
}
