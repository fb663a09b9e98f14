//! PNG plots (plotters, bitmap backend, bundled DejaVu Sans).

use crate::flight::Row;
use anyhow::{anyhow, Result};
use plotters::prelude::*;
use plotters::style::FontStyle;
use std::path::Path;
use std::sync::Once;

static FONT: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

fn register() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT);
    });
}

const FLOOR_PX: f64 = 0.01;

/// Colours of the policies in overlaid plots.
const POLICY_COLOURS: [RGBColor; 4] = [
    RGBColor(200, 30, 30),
    RGBColor(30, 90, 200),
    RGBColor(20, 150, 60),
    RGBColor(140, 60, 170),
];

/// One link, every policy overlaid: max SSE, mean SSE per pixel and the
/// largest true error at the probes, each against time (left) and against
/// megabytes received (right), log scales floored at 0.01. The tolerance is
/// drawn as a grey line.
pub fn policies_plot(
    path: &Path,
    title: &str,
    runs: &[(String, Vec<Row>)],
    tolerance: f64,
    floor: Option<&[(f64, f64)]>,
) -> Result<()> {
    register();
    let root = BitMapBackend::new(path, (1400, 1300)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| anyhow!("{e}"))?;
    let root = root
        .titled(title, ("sans-serif", 24))
        .map_err(|e| anyhow!("{e}"))?;
    let panels = root.split_evenly((3, 2));
    let all = || runs.iter().flat_map(|r| r.1.iter());
    let t_max = all().map(|r| r.t).fold(1e-3, f64::max);
    let mb_max = all()
        .map(|r| r.bytes_total as f64 / 1e6)
        .fold(1e-3, f64::max);
    let sse_hi = all().map(|r| r.sse_max).fold(1.0, f64::max) * 1.5;
    let err_hi = all()
        .map(|r| r.err_max)
        .filter(|v| v.is_finite())
        .fold(1.0, f64::max)
        * 1.5;
    type Get = fn(&Row) -> Option<(f64, f64)>;
    let panels_spec: [(&str, &str, f64, f64, Get); 6] = [
        ("time (s)", "max SSE (px)", t_max, sse_hi, |r| {
            Some((r.t, r.sse_max))
        }),
        ("received (MB)", "max SSE (px)", mb_max, sse_hi, |r| {
            Some((r.bytes_total as f64 / 1e6, r.sse_max))
        }),
        ("time (s)", "mean SSE per pixel (px)", t_max, sse_hi, |r| {
            Some((r.t, r.sse_pixel_mean))
        }),
        (
            "received (MB)",
            "mean SSE per pixel (px)",
            mb_max,
            sse_hi,
            |r| Some((r.bytes_total as f64 / 1e6, r.sse_pixel_mean)),
        ),
        (
            "time (s)",
            "max true error at probes (m)",
            t_max,
            err_hi,
            |r| (r.probes > 0 && r.err_max.is_finite()).then_some((r.t, r.err_max)),
        ),
        (
            "received (MB)",
            "max true error at probes (m)",
            mb_max,
            err_hi,
            |r| {
                (r.probes > 0 && r.err_max.is_finite())
                    .then_some((r.bytes_total as f64 / 1e6, r.err_max))
            },
        ),
    ];
    for (k, (area, (xl, yl, x_max, y_hi, get))) in panels.iter().zip(panels_spec).enumerate() {
        let y_lo = FLOOR_PX;
        let mut chart = ChartBuilder::on(area)
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..x_max, (y_lo..y_hi).log_scale())
            .map_err(|e| anyhow!("{e}"))?;
        chart
            .configure_mesh()
            .x_desc(xl)
            .y_desc(yl)
            .label_style(("sans-serif", 14))
            .draw()
            .map_err(|e| anyhow!("{e}"))?;
        for (i, (name, rows)) in runs.iter().enumerate() {
            let c = POLICY_COLOURS[i % POLICY_COLOURS.len()];
            let pts: Vec<(f64, f64)> = rows
                .iter()
                .filter_map(get)
                .map(|(x, y)| (x, y.max(y_lo)))
                .collect();
            chart
                .draw_series(LineSeries::new(pts, c.stroke_width(2)))
                .map_err(|e| anyhow!("{e}"))?
                .label(name.as_str())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2))
                });
        }
        if let Some(f) = floor.filter(|_| k == 2) {
            let pts: Vec<(f64, f64)> = f.iter().map(|&(t, y)| (t, y.max(y_lo))).collect();
            let c = BLACK.mix(0.7);
            chart
                .draw_series(DashedLineSeries::new(pts, 6, 4, c.stroke_width(2)))
                .map_err(|e| anyhow!("{e}"))?
                .label("floor (every request answered at once)")
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c));
        }
        if k < 4 {
            chart
                .draw_series(LineSeries::new(
                    vec![(0.0, tolerance), (x_max, tolerance)],
                    BLACK.mix(0.4),
                ))
                .map_err(|e| anyhow!("{e}"))?
                .label("tolerance")
                .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK.mix(0.4)));
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font(("sans-serif", 14))
            .draw()
            .map_err(|e| anyhow!("{e}"))?;
    }
    root.present().map_err(|e| anyhow!("{e}"))?;
    Ok(())
}
