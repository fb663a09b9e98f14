//! The on-screen readout: lines of text rasterised with an 8×8 bitmap font
//! (font8x8, public domain) into an RGBA image over a translucent panel.

use font8x8::legacy::BASIC_LEGACY;

/// A rasterised text panel, RGBA8 (sRGB, straight alpha), row 0 at the top.
#[derive(Debug, Clone, PartialEq)]
pub struct Panel {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Pixels.
    pub rgba: Vec<u8>,
}

const PAD: u32 = 4;
const LINE: u32 = 10;

/// Rasterise `lines` at integer `scale`.
pub fn rasterise(lines: &[String], scale: u32) -> Panel {
    let scale = scale.max(1);
    let cols = lines.iter().map(|l| l.chars().count()).max().unwrap_or(0) as u32;
    let width = (cols * 8 + 2 * PAD) * scale;
    let height = (lines.len() as u32 * LINE + 2 * PAD) * scale;
    let mut rgba = vec![0u8; (width * height * 4) as usize];
    for px in rgba.chunks_exact_mut(4) {
        px.copy_from_slice(&[0, 0, 0, 150]);
    }
    for (row, line) in lines.iter().enumerate() {
        for (col, ch) in line.chars().enumerate() {
            let code = ch as usize;
            let glyph = if code < 128 {
                BASIC_LEGACY[code]
            } else {
                BASIC_LEGACY[b'?' as usize]
            };
            for (gy, bits) in glyph.iter().enumerate() {
                for gx in 0..8u32 {
                    if bits & (1 << gx) == 0 {
                        continue;
                    }
                    let x0 = (PAD + col as u32 * 8 + gx) * scale;
                    let y0 = (PAD + row as u32 * LINE + gy as u32) * scale;
                    for dy in 0..scale {
                        for dx in 0..scale {
                            let k = (((y0 + dy) * width + x0 + dx) * 4) as usize;
                            rgba[k..k + 4].copy_from_slice(&[240, 240, 200, 255]);
                        }
                    }
                }
            }
        }
    }
    Panel {
        width: width.max(1),
        height: height.max(1),
        rgba,
    }
}

/// A byte count for humans.
pub fn bytes(n: u64) -> String {
    let n = n as f64;
    if n >= 1e9 {
        format!("{:.2} GB", n / 1e9)
    } else if n >= 1e6 {
        format!("{:.2} MB", n / 1e6)
    } else if n >= 1e3 {
        format!("{:.1} kB", n / 1e3)
    } else {
        format!("{n} B")
    }
}

/// A distance for humans.
pub fn metres(m: f64) -> String {
    if m.abs() >= 1e4 {
        format!("{:.0} km", m / 1e3)
    } else if m.abs() >= 1e3 {
        format!("{:.2} km", m / 1e3)
    } else {
        format!("{m:.0} m")
    }
}

/// A latitude and longitude for humans: `46.8500N 121.7600W` (ASCII: the HUD font has no degree sign).
pub fn lat_lon(lat: f64, lon: f64) -> String {
    // Longitudes in (-180, 180]: the controller lets them run on.
    let lon = -((-lon + 180.0).rem_euclid(360.0) - 180.0);
    format!(
        "{:.4}{} {:.4}{}",
        lat.abs(),
        if lat >= 0.0 { 'N' } else { 'S' },
        lon.abs(),
        if lon >= 0.0 { 'E' } else { 'W' }
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lat_lon_wraps_and_names_hemispheres() {
        assert_eq!(lat_lon(46.85, -121.76), "46.8500N 121.7600W");
        assert_eq!(lat_lon(-17.5, 540.0), "17.5000S 180.0000E");
        assert_eq!(lat_lon(0.0, 181.0), "0.0000N 179.0000W");
        assert_eq!(lat_lon(-90.0, -180.0), "90.0000S 180.0000E");
    }

    #[test]
    fn text_sets_pixels() {
        let p = rasterise(&["AB 12".to_string(), "x".to_string()], 2);
        assert_eq!(p.width, (5 * 8 + 8) * 2);
        assert_eq!(p.height, (2 * 10 + 8) * 2);
        let lit = p.rgba.chunks_exact(4).filter(|c| c[3] == 255).count();
        assert!(lit > 50);
        assert_eq!(bytes(1_500_000), "1.50 MB");
        assert_eq!(metres(4392.0), "4.39 km");
    }
}
