//! Raster inputs named on the command line: files, directories of tiles
//! and list files, expanded once into the list of rasters to open.
//!
//! - A directory stands for every raster under it (recursively): files
//!   named `*.tif`, `*.tiff` or `*.hgt` (any case), in path order.
//! - A file named `*.txt` or `*.list` is a list of rasters, one path per
//!   line (relative paths from the list's own directory; blank lines and
//!   lines starting with `#` are skipped); its entries may be directories.
//! - Anything else is a raster.

use crate::error::GeoError;
use std::path::{Path, PathBuf};

/// Whether a file name is a raster's (`.tif`, `.tiff`, `.hgt`).
pub fn is_raster_name(p: &Path) -> bool {
    p.extension().and_then(|e| e.to_str()).is_some_and(|e| {
        ["tif", "tiff", "hgt"]
            .iter()
            .any(|x| e.eq_ignore_ascii_case(x))
    })
}

fn is_list_name(p: &Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("txt") || e.eq_ignore_ascii_case("list"))
}

fn open_err(path: &Path, source: std::io::Error) -> GeoError {
    GeoError::Open {
        path: path.to_path_buf(),
        source,
    }
}

/// The rasters `paths` name, in order (see the module documentation); an
/// empty directory or list is an error naming it.
pub fn expand(paths: &[PathBuf]) -> Result<Vec<PathBuf>, GeoError> {
    let mut out = Vec::new();
    for p in paths {
        let before = out.len();
        expand_one(p, &mut out, 0)?;
        if out.len() == before {
            return Err(GeoError::Georeference {
                path: p.clone(),
                what: "no raster (.tif, .tiff, .hgt) found in it".into(),
            });
        }
    }
    Ok(out)
}

fn expand_one(p: &Path, out: &mut Vec<PathBuf>, depth: usize) -> Result<(), GeoError> {
    if p.is_dir() {
        let mut found = Vec::new();
        let mut dirs = vec![p.to_path_buf()];
        while let Some(d) = dirs.pop() {
            for e in std::fs::read_dir(&d).map_err(|e| open_err(&d, e))? {
                let path = e.map_err(|e| open_err(&d, e))?.path();
                if path.is_dir() {
                    dirs.push(path);
                } else if is_raster_name(&path) {
                    found.push(path);
                }
            }
        }
        found.sort();
        out.extend(found);
    } else if is_list_name(p) && depth < 4 {
        let text = std::fs::read_to_string(p).map_err(|e| open_err(p, e))?;
        let base = p.parent().unwrap_or(Path::new("."));
        for line in text.lines().map(str::trim) {
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            expand_one(&base.join(line), out, depth + 1)?;
        }
    } else {
        out.push(p.to_path_buf());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn directories_and_lists_expand_in_order() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        std::fs::create_dir_all(d.join("tiles/sub")).unwrap();
        for f in [
            "tiles/b.tif",
            "tiles/a.TIF",
            "tiles/sub/c.hgt",
            "tiles/notes.md",
        ] {
            std::fs::write(d.join(f), b"").unwrap();
        }
        std::fs::write(
            d.join("list.txt"),
            "# tiles\n\ntiles/sub/c.hgt\n  tiles  \n",
        )
        .unwrap();
        let got = expand(&[d.join("tiles"), d.join("list.txt"), d.join("x.tif")]).unwrap();
        let want: Vec<PathBuf> = [
            "tiles/a.TIF",
            "tiles/b.tif",
            "tiles/sub/c.hgt",
            "tiles/sub/c.hgt",
            "tiles/a.TIF",
            "tiles/b.tif",
            "tiles/sub/c.hgt",
            "x.tif",
        ]
        .iter()
        .map(|f| d.join(f))
        .collect();
        assert_eq!(got, want);
        std::fs::create_dir(d.join("empty")).unwrap();
        let e = expand(&[d.join("empty")]).unwrap_err().to_string();
        assert!(e.contains("empty") && e.contains("no raster"), "{e}");
    }
}
