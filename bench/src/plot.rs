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
const FLOOR_M: f64 = 0.01;

/// Four panels: max/mean SSE and true error (max/mean) against time and
/// against megabytes received (log-scaled errors, floored at 0.01).
pub fn flight_plot(path: &Path, title: &str, rows: &[Row]) -> Result<()> {
    register();
    let root = BitMapBackend::new(path, (1400, 900)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| anyhow!("{e}"))?;
    let root = root
        .titled(title, ("sans-serif", 24))
        .map_err(|e| anyhow!("{e}"))?;
    let panels = root.split_evenly((2, 2));
    let t_max = rows.last().map_or(1.0, |r| r.t).max(1e-3);
    let mb_max = rows
        .last()
        .map_or(1.0, |r| r.bytes_total as f64 / 1e6)
        .max(1e-3);
    let sse_hi = rows.iter().map(|r| r.sse_max).fold(1.0, f64::max) * 1.5;
    let err_hi = rows
        .iter()
        .map(|r| r.err_max)
        .filter(|v| v.is_finite())
        .fold(1.0, f64::max)
        * 1.5;
    for (k, area) in panels.iter().enumerate() {
        let by_time = k % 2 == 0;
        let sse = k < 2;
        let x_max = if by_time { t_max } else { mb_max };
        let (y_lo, y_hi) = if sse {
            (FLOOR_PX, sse_hi)
        } else {
            (FLOOR_M, err_hi)
        };
        let x_label = if by_time { "time (s)" } else { "received (MB)" };
        let y_label = if sse {
            "screen-space error (px)"
        } else {
            "true error at probes (m)"
        };
        let mut chart = ChartBuilder::on(area)
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..x_max, (y_lo..y_hi).log_scale())
            .map_err(|e| anyhow!("{e}"))?;
        chart
            .configure_mesh()
            .x_desc(x_label)
            .y_desc(y_label)
            .label_style(("sans-serif", 14))
            .draw()
            .map_err(|e| anyhow!("{e}"))?;
        let x = |r: &Row| {
            if by_time {
                r.t
            } else {
                r.bytes_total as f64 / 1e6
            }
        };
        let (a, b, la, lb) = if sse {
            (
                rows.iter()
                    .map(|r| (x(r), r.sse_max.max(y_lo)))
                    .collect::<Vec<_>>(),
                rows.iter()
                    .map(|r| (x(r), r.sse_mean.max(y_lo)))
                    .collect::<Vec<_>>(),
                "max SSE",
                "mean SSE",
            )
        } else {
            (
                rows.iter()
                    .filter(|r| r.probes > 0)
                    .map(|r| (x(r), r.err_max.max(y_lo)))
                    .collect::<Vec<_>>(),
                rows.iter()
                    .filter(|r| r.probes > 0)
                    .map(|r| (x(r), r.err_mean.max(y_lo)))
                    .collect::<Vec<_>>(),
                "max true error",
                "mean true error",
            )
        };
        chart
            .draw_series(LineSeries::new(a, RED.stroke_width(2)))
            .map_err(|e| anyhow!("{e}"))?
            .label(la)
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED.stroke_width(2)));
        chart
            .draw_series(LineSeries::new(b, BLUE.stroke_width(2)))
            .map_err(|e| anyhow!("{e}"))?
            .label(lb)
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLUE.stroke_width(2)));
        if sse {
            chart
                .draw_series(LineSeries::new(
                    vec![(0.0, 1.0), (x_max, 1.0)],
                    BLACK.mix(0.4),
                ))
                .map_err(|e| anyhow!("{e}"))?
                .label("1 px")
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
