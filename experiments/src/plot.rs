//! SVG plots with plotters: line plots of curves (training losses, metric curves)
//! and shares with their intervals against a log axis (a power study's curves).

use std::fmt::Display;
use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;

use crate::output::write_atomic;

/// A curve of `(x, y)` points, e.g. `(training step, value)`.
pub type Curve = Vec<(f64, f64)>;

/// One named curve of (x, y) points.
pub struct Series {
    pub name: String,
    pub points: Curve,
}

/// The size of every chart, in pixels.
const CHART_SIZE: (u32, u32) = (800, 500);
/// The width of a legend drawn beside its chart, in pixels.
const LEGEND_WIDTH: u32 = 230;

/// A chart's drawing area, in memory.
pub type Canvas<'a> = DrawingArea<SVGBackend<'a>, Shift>;

/// Renders an SVG of `size` pixels in memory — `draw` is given the white canvas
/// and an error formatter naming `path` — and writes it to `path` through a
/// temporary file, so an existing picture is replaced whole or not at all. Every
/// picture the program draws goes through here.
pub fn write_svg(
    path: &Path,
    size: (u32, u32),
    draw: impl FnOnce(&Canvas, &dyn Fn(&dyn Display) -> String) -> Result<(), String>,
) -> Result<(), String> {
    let err = |e: &dyn Display| format!("{}: {e}", path.display());
    let mut svg = String::new();
    {
        let root: Canvas = SVGBackend::with_string(&mut svg, size).into_drawing_area();
        root.fill(&WHITE).map_err(|e| err(&e))?;
        draw(&root, &err)?;
        root.present().map_err(|e| err(&e))?;
    }
    write_atomic(path, svg.as_bytes())
}

/// The canvas below a chart's caption `title`.
fn titled<'a>(root: &Canvas<'a>, title: &str, err: &dyn Fn(&dyn Display) -> String) -> Result<Canvas<'a>, String> {
    root.titled(title, ("sans-serif", 22)).map_err(|e| err(&e))
}

/// A chart's frame on `area`: its margin and label areas.
fn frame<'a, 'b>(area: &'a Canvas<'b>) -> ChartBuilder<'a, 'b, SVGBackend<'b>> {
    let mut builder = ChartBuilder::on(area);
    builder.margin(12).x_label_area_size(40).y_label_area_size(60);
    builder
}

/// Draws `series` as lines on one chart and writes it to `path` as SVG.
pub fn line_chart(path: &Path, title: &str, x_label: &str, y_label: &str, series: &[Series]) -> Result<(), String> {
    let finite = |v: f64| v.is_finite();
    let pts = series.iter().flat_map(|s| s.points.iter()).filter(|(x, y)| finite(*x) && finite(*y));
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y) in pts {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    if x0 > x1 {
        return Err(format!("{}: nothing finite to plot", path.display()));
    }
    let pad = ((y1 - y0) * 0.05).max(1e-9);
    let (y0, y1) = (y0 - pad, y1 + pad);
    let x1 = if x1 > x0 { x1 } else { x0 + 1.0 };
    write_svg(path, CHART_SIZE, |root, err| {
        let area = titled(root, title, err)?;
        let mut chart = frame(&area).build_cartesian_2d(x0..x1, y0..y1).map_err(|e| err(&e))?;
        chart.configure_mesh().x_desc(x_label).y_desc(y_label).draw().map_err(|e| err(&e))?;
        for (i, s) in series.iter().enumerate() {
            let color = Palette99::pick(i).to_rgba();
            chart
                .draw_series(LineSeries::new(s.points.iter().copied(), color.stroke_width(2)))
                .map_err(|e| err(&e))?
                .label(s.name.clone())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
        }
        chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw().map_err(|e| err(&e))
    })
}

/// A share between 0 and 1 at one `x`, with its interval (`low..=high`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Share {
    pub x: f64,
    pub share: f64,
    pub low: f64,
    pub high: f64,
}

/// One named series of shares, e.g. an effect's share of seeds named at each strength.
pub struct ShareSeries {
    pub name: String,
    pub shares: Vec<Share>,
}

/// Draws each series' shares against `x` on a log axis — a line through the
/// points and each interval as a vertical bar, the series set a little apart
/// along `x` so that equal shares stay visible — with `goal`, if any, as a
/// dashed line and the legend beside the chart, and writes the chart to `path`
/// as SVG. `x` must be positive; the axis is labelled at its powers of 2.
pub fn share_chart(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[ShareSeries],
    goal: Option<f64>,
) -> Result<(), String> {
    let xs = series.iter().flat_map(|s| s.shares.iter().map(|p| p.x));
    let (x0, x1) = xs.fold((f64::MAX, f64::MIN), |(lo, hi), x| (lo.min(x), hi.max(x)));
    if !(x0 > 0.0 && x1.is_finite()) {
        return Err(format!("{}: a share chart needs positive, finite x", path.display()));
    }
    // Drawn in octaves (log2 x). The series sit side by side within 0.3 of an
    // octave of each point; the axis reaches half an octave past the outer points.
    let octave = |p: &Share, i: usize| p.x.log2() + 0.3 * ((i as f64 + 0.5) / series.len() as f64 - 0.5);
    let (lo, hi) = (x0.log2().floor() - 0.5, x1.log2().ceil() + 0.5);
    let black = BLACK.stroke_width(1);
    write_svg(path, CHART_SIZE, |root, err| {
        // (name, style, dashed) of each entry, drawn beside the chart.
        let mut legend: Vec<(String, ShapeStyle, bool)> = Vec::new();
        let (plot, side) = titled(root, title, err)?.split_horizontally(CHART_SIZE.0 - LEGEND_WIDTH);
        let mut chart = frame(&plot).build_cartesian_2d(lo..hi, -0.02..1.02).map_err(|e| err(&e))?;
        chart
            .configure_mesh()
            .disable_x_mesh()
            .light_line_style(WHITE)
            .x_labels(2 * (hi - lo) as usize + 1)
            .x_label_formatter(&|x| if x.fract() == 0.0 { format!("{}", x.exp2()) } else { String::new() })
            .y_label_formatter(&|y| format!("{:.0}%", 100.0 * y))
            .x_desc(x_label)
            .y_desc(y_label)
            .draw()
            .map_err(|e| err(&e))?;
        if let Some(goal) = goal {
            chart.draw_series(DashedLineSeries::new(vec![(lo, goal), (hi, goal)], 6, 4, black)).map_err(|e| err(&e))?;
            legend.push((format!("goal ({:.0}%)", 100.0 * goal), black, true));
        }
        for (i, s) in series.iter().enumerate() {
            let color = Palette99::pick(i).to_rgba();
            let at = |p: &Share| (octave(p, i), p.share);
            chart.draw_series(LineSeries::new(s.shares.iter().map(at), color.stroke_width(2))).map_err(|e| err(&e))?;
            chart.draw_series(s.shares.iter().map(|p| Circle::new(at(p), 4, color.filled()))).map_err(|e| err(&e))?;
            let bars =
                s.shares.iter().map(|p| PathElement::new(vec![(octave(p, i), p.low), (octave(p, i), p.high)], color));
            chart.draw_series(bars).map_err(|e| err(&e))?;
            legend.push((s.name.clone(), color.stroke_width(2), false));
        }
        for (k, (name, style, dashed)) in legend.iter().enumerate() {
            let y = 30 + 22 * k as i32;
            let segments = if *dashed { vec![(4, 10), (16, 22)] } else { vec![(4, 22)] };
            for (from, to) in segments {
                side.draw(&PathElement::new(vec![(from, y), (to, y)], *style)).map_err(|e| err(&e))?;
            }
            side.draw(&Text::new(name.clone(), (28, y - 7), ("sans-serif", 13))).map_err(|e| err(&e))?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A share chart holds every series and the goal in its legend, and
    /// refuses an x it cannot draw on a log axis, leaving no file behind.
    #[test]
    fn a_share_chart_draws_every_series_and_refuses_a_nonpositive_x() {
        let dir = std::env::temp_dir().join(format!("sefi-share-chart-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let share = |x: f64, share: f64| Share { x, share, low: share * 0.5, high: 1.0 };
        let series = [
            ShareSeries { name: "weak".into(), shares: vec![share(0.5, 0.2), share(1.0, 0.6), share(2.0, 1.0)] },
            ShareSeries { name: "strong".into(), shares: vec![share(1.0, 1.0)] },
        ];
        let path = dir.join("shares.svg");
        share_chart(&path, "shares", "x", "share", &series, Some(0.9)).unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        // The legend's entries and the axes' labels, each as a text element.
        let texts = ["weak", "strong", "goal (90%)", "0.5", "2", "100%", "0%"];
        let drawn: Vec<&str> = svg
            .split("</text>")
            .filter_map(|part| part.rsplit_once("<text").and_then(|(_, element)| element.split_once('>')))
            .map(|(_, content)| content.trim())
            .collect();
        assert!(texts.iter().all(|t| drawn.contains(t)), "{drawn:?}");
        let bad = [ShareSeries { name: "zero".into(), shares: vec![share(0.0, 0.5)] }];
        let err = share_chart(&dir.join("bad.svg"), "bad", "x", "share", &bad, None).unwrap_err();
        assert!(err.contains("bad.svg") && err.contains("positive"), "{err}");
        assert!(!dir.join("bad.svg").exists());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
