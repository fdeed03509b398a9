//! Error-against-time plots of the accuracy study (plotters; PNG and SVG).
//!
//! The text is drawn with DejaVu Sans Mono, embedded in the binary (its licence is in
//! `coordinator/assets/DejaVu-LICENSE.txt`), so a machine without system fonts draws the
//! same plot.

use super::Point;
use anyhow::{anyhow, Result};
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::Path;
use std::sync::OnceLock;

static FONT: &[u8] = include_bytes!("../../assets/DejaVuSansMono.ttf");

fn register_font() -> Result<()> {
    static DONE: OnceLock<Result<(), String>> = OnceLock::new();
    DONE.get_or_init(|| {
        plotters::style::register_font("sans-serif", FontStyle::Normal, FONT)
            .map_err(|_| "the embedded plot font does not load".to_string())
    })
    .clone()
    .map_err(|e| anyhow!(e))
}

/// Errors are drawn on a log axis; an exact match sits at this floor.
const FLOOR: f64 = 1e-7;

fn y_of(p: &Point) -> f64 {
    p.errors.rmse.max(FLOOR)
}

fn x_of(p: &Point) -> f64 {
    (p.seconds * 1e3).max(1e-3)
}

/// Draws one knob's points over all the others, the Pareto front of all points and the
/// defaults, to `stem.png` and `stem.svg`.
pub fn knob_plot(
    stem: &Path,
    title: &str,
    points: &[Point],
    knob: &str,
    front: &[usize],
    defaults: usize,
) -> Result<()> {
    register_font()?;
    let png = stem.with_extension("png");
    let svg = stem.with_extension("svg");
    {
        let root = BitMapBackend::new(&png, (900, 620)).into_drawing_area();
        draw(root, title, points, knob, front, defaults)
            .map_err(|e| anyhow!("{}: {e}", png.display()))?;
    }
    {
        let root = SVGBackend::new(&svg, (900, 620)).into_drawing_area();
        draw(root, title, points, knob, front, defaults)
            .map_err(|e| anyhow!("{}: {e}", svg.display()))?;
    }
    Ok(())
}

fn draw<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    title: &str,
    points: &[Point],
    knob: &str,
    front: &[usize],
    defaults: usize,
) -> Result<(), String> {
    let e = |x: DrawingAreaErrorKind<DB::ErrorType>| format!("{x:?}");
    root.fill(&WHITE).map_err(e)?;
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for p in points {
        x0 = x0.min(x_of(p));
        x1 = x1.max(x_of(p));
        y0 = y0.min(y_of(p));
        y1 = y1.max(y_of(p));
    }
    let (x0, x1, y0, y1) = (x0 / 1.5, x1 * 1.5, y0 / 2.0, y1 * 2.0);
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(75)
        .build_cartesian_2d((x0..x1).log_scale(), (y0..y1).log_scale())
        .map_err(e)?;
    chart
        .configure_mesh()
        .x_desc("time per frame (ms)")
        .y_desc("RMSE vs reference (premultiplied linear RGBA)")
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .label_style(("sans-serif", 13))
        .draw()
        .map_err(e)?;
    let grey = RGBColor(190, 190, 190);
    chart
        .draw_series(
            points
                .iter()
                .filter(|p| p.knob != knob)
                .map(|p| Circle::new((x_of(p), y_of(p)), 3, grey.filled())),
        )
        .map_err(e)?
        .label("other knobs")
        .legend(move |(x, y)| Circle::new((x + 10, y), 3, grey.filled()));
    // The front as a staircase: each point holds its error until a faster-and-better one.
    let mut stair = Vec::new();
    for (n, &i) in front.iter().enumerate() {
        let p = (x_of(&points[i]), y_of(&points[i]));
        if n > 0 {
            stair.push((p.0, stair.last().map_or(p.1, |q: &(f64, f64)| q.1)));
        }
        stair.push(p);
    }
    if let Some(&(_, y)) = stair.last() {
        stair.push((x1, y));
    }
    chart
        .draw_series(LineSeries::new(stair, BLACK.stroke_width(1)))
        .map_err(e)?
        .label("Pareto front (all points)")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK));
    let blue = RGBColor(30, 90, 200);
    chart
        .draw_series(
            points
                .iter()
                .filter(|p| p.knob == knob)
                .map(|p| Circle::new((x_of(p), y_of(p)), 5, blue.filled())),
        )
        .map_err(e)?
        .label(knob.to_string())
        .legend(move |(x, y)| Circle::new((x + 10, y), 5, blue.filled()));
    chart
        .draw_series(points.iter().filter(|p| p.knob == knob).map(|p| {
            Text::new(
                p.label.clone(),
                (x_of(p) * 1.04, y_of(p) * 1.08),
                ("sans-serif", 12),
            )
        }))
        .map_err(e)?;
    let d = &points[defaults];
    chart
        .draw_series(std::iter::once(Cross::new(
            (x_of(d), y_of(d)),
            9,
            RED.stroke_width(3),
        )))
        .map_err(e)?
        .label("defaults")
        .legend(|(x, y)| Cross::new((x + 10, y), 6, RED.stroke_width(3)));
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 13))
        .draw()
        .map_err(e)?;
    root.present().map_err(e)?;
    Ok(())
}
