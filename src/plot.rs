//! Line charts as PNG files, with no system fonts: the font (DejaVu Sans, licence in
//! `assets/DejaVuSans.LICENSE`) is compiled in and registered with plotters once.

use crate::error::{Error, ErrorKind, Result};
use plotters::prelude::*;
use plotters::style::{register_font, FontStyle};
use std::path::Path;
use std::sync::Once;

static FONT: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

/// Register the compiled-in font as "sans-serif" (once). Every plotters backend that
/// draws text (PNG here, SVG in `diag::report`) needs it: no system fonts are used.
pub fn ensure_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The font is compiled in and known to parse; a failure would leave text unset,
        // never a crash.
        let _ = register_font("sans-serif", FontStyle::Normal, FONT);
    });
}

/// One named line.
#[derive(Debug, Clone)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
}

/// A chart of several lines sharing axes.
#[derive(Debug, Clone)]
pub struct Chart {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    /// Logarithmic y axis (points with y <= 0 are left out).
    pub log_y: bool,
    pub series: Vec<Series>,
    /// Horizontal reference lines (value, label), e.g. thresholds.
    pub hlines: Vec<(f64, String)>,
}

const COLOURS: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(127, 127, 127),
];

fn plot_err(path: &Path, e: impl std::fmt::Display) -> Error {
    Error::new(ErrorKind::Io, format!("plotting failed: {e}")).path(path)
}

/// Draw `chart` into a `width x height` PNG at `path`.
pub fn line_chart_png(path: &Path, chart: &Chart, width: u32, height: u32) -> Result<()> {
    ensure_font();
    let keep = |y: f64| y.is_finite() && (!chart.log_y || y > 0.0);
    let pts = chart
        .series
        .iter()
        .flat_map(|s| s.points.iter())
        .filter(|p| p.0.is_finite() && keep(p.1));
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y) in pts {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    for (y, _) in &chart.hlines {
        if keep(*y) {
            y0 = y0.min(*y);
            y1 = y1.max(*y);
        }
    }
    if x0 > x1 || y0 > y1 {
        return Err(plot_err(path, "no finite points to plot"));
    }
    if x1 == x0 {
        x1 = x0 + 1.0;
    }
    let (y0, y1) = if chart.log_y {
        (y0 / 2.0, y1 * 2.0)
    } else {
        let pad = ((y1 - y0) * 0.05).max(1e-12);
        (y0 - pad, y1 + pad)
    };
    let root = BitMapBackend::new(path, (width, height)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| plot_err(path, e))?;
    let mut builder = ChartBuilder::on(&root);
    builder
        .caption(&chart.title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(42)
        .y_label_area_size(70);
    macro_rules! draw {
        ($ctx:expr) => {{
            let mut ctx = $ctx;
            ctx.configure_mesh()
                .x_desc(chart.x_label.as_str())
                .y_desc(chart.y_label.as_str())
                .label_style(("sans-serif", 14))
                .draw()
                .map_err(|e| plot_err(path, e))?;
            for (i, (y, label)) in chart.hlines.iter().enumerate() {
                let style = BLACK.mix(0.6).stroke_width(2);
                ctx.draw_series(LineSeries::new(vec![(x0, *y), (x1, *y)], style))
                    .map_err(|e| plot_err(path, e))?
                    .label(label.as_str())
                    .legend(move |(x, y)| {
                        PathElement::new(
                            vec![(x, y), (x + 18, y)],
                            COLOURS[5].mix(0.8 - 0.2 * i as f64),
                        )
                    });
            }
            for (i, s) in chart.series.iter().enumerate() {
                let colour = COLOURS[i % 5];
                let pts: Vec<(f64, f64)> = s
                    .points
                    .iter()
                    .copied()
                    .filter(|p| p.0.is_finite() && keep(p.1))
                    .collect();
                ctx.draw_series(LineSeries::new(pts, colour.stroke_width(2)))
                    .map_err(|e| plot_err(path, e))?
                    .label(s.name.as_str())
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(2))
                    });
            }
            ctx.configure_series_labels()
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .label_font(("sans-serif", 14))
                .draw()
                .map_err(|e| plot_err(path, e))?;
        }};
    }
    if chart.log_y {
        draw!(builder
            .build_cartesian_2d(x0..x1, (y0..y1).log_scale())
            .map_err(|e| plot_err(path, e))?);
    } else {
        draw!(builder
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(|e| plot_err(path, e))?);
    }
    root.present().map_err(|e| plot_err(path, e))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_a_png_with_lines() {
        let tmp = tempfile::tempdir().unwrap();
        let p = tmp.path().join("c.png");
        let chart = Chart {
            title: "test".into(),
            x_label: "t [s]".into(),
            y_label: "i [e-/s]".into(),
            log_y: true,
            series: vec![Series {
                name: "1/t".into(),
                points: (1..100).map(|t| (t as f64, 1.0 / t as f64)).collect(),
            }],
            hlines: vec![(0.1, "0.1 e-/s".into())],
        };
        line_chart_png(&p, &chart, 640, 400).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        assert_eq!(&bytes[1..4], b"PNG");
        assert!(bytes.len() > 5000, "{}", bytes.len());
        let empty = Chart {
            series: vec![],
            hlines: vec![],
            ..chart
        };
        assert!(line_chart_png(&p, &empty, 64, 64).is_err());
    }
}
