//! A bird's-eye view of one scene (SVG), in the style of the paper's figures: the
//! AV's track and pose, the true boxes (when the dataset has true states), the
//! observations (points or detected boxes) and the estimated tracks, with a legend.
//! World frame, metres, equal scale on both axes.

use std::path::Path;

use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use ssm::data::{BoxDetection, Dataset, State};
use ssm::evaluation::metrics::Tracks;

use crate::plot::write_svg;

/// Assumed AV footprint (m): the dataset gives its pose only.
const AV_LENGTH: f64 = 4.5;
const AV_WIDTH: f64 = 1.9;
/// Margin around everything drawn (m).
const MARGIN: f64 = 4.0;
/// Width of the figure (px); the height follows the scene's aspect ratio.
const WIDTH_PX: u32 = 1100;
/// Space for the title, axis labels and margins (px).
const FRAME_PX: (u32, u32) = (90, 100);
/// A true box is outlined at every k-th step (and the last), so boxes do not merge.
const BOX_EVERY: usize = 3;

const TRUE_COLOUR: RGBColor = RGBColor(46, 139, 87);
const OBS_COLOUR: RGBColor = RGBColor(230, 97, 1);
const SMOOTH_COLOUR: RGBColor = RGBColor(33, 102, 172);
const FILTER_COLOUR: RGBColor = RGBColor(146, 197, 222);
const AV_COLOUR: RGBColor = RGBColor(40, 40, 40);

/// Corners of a `length x width` box centred at `(x, y)` with heading `yaw`.
fn corners(x: f64, y: f64, yaw: f64, length: f64, width: f64) -> Vec<(f64, f64)> {
    let (c, s) = (yaw.cos(), yaw.sin());
    let (hl, hw) = (length / 2.0, width / 2.0);
    [(hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw)].iter().map(|&(a, b)| (x + a * c - b * s, y + a * s + b * c)).collect()
}

/// The outline of a box as one path that starts at its centre, goes to the middle of
/// the front edge (a tick showing the heading) and then round the four corners.
fn outline(x: f64, y: f64, yaw: f64, length: f64, width: f64) -> Vec<(f64, f64)> {
    let c = corners(x, y, yaw, length, width);
    let front = ((c[0].0 + c[3].0) / 2.0, (c[0].1 + c[3].1) / 2.0);
    vec![(x, y), front, c[0], c[1], c[2], c[3], front]
}

/// The outline of a box without the heading tick.
fn rectangle(x: f64, y: f64, yaw: f64, length: f64, width: f64) -> Vec<(f64, f64)> {
    let mut c = corners(x, y, yaw, length, width);
    c.push(c[0]);
    c
}

/// Draws scene `scene` (an index into `data.scenes()`) with the estimates of
/// `tracks` into an SVG at `path`.
pub fn draw(path: &Path, data: &Dataset, scene_index: usize, tracks: &Tracks, lag: usize) -> Result<(), String> {
    let scene = &data.scenes()[scene_index];
    let objects: Vec<usize> = scene.objects.clone().collect();
    let steps = data.steps();
    let truth = data.states();
    let true_state = |o: usize, t: usize| truth.and_then(|s| s.get(o, t)).copied();
    let detection = |o: usize, t: usize| -> Option<BoxDetection> { data.boxes().and_then(|b| b.get(o, t)).copied() };
    let points = |o: usize, t: usize| -> &[[f64; 2]] { data.points().map_or(&[], |p| p.get(o, t)) };

    // Extent of everything drawn.
    let mut xs: Vec<f64> = Vec::new();
    let mut ys: Vec<f64> = Vec::new();
    let mut see = |x: f64, y: f64| {
        if x.is_finite() && y.is_finite() {
            xs.push(x);
            ys.push(y);
        }
    };
    for p in &scene.av {
        see(p.x, p.y);
    }
    for &o in &objects {
        for t in 0..steps {
            if let Some(s) = true_state(o, t) {
                see(s.x, s.y);
            }
            if let Some(e) = tracks.smoothed.get(o).and_then(|r| r.get(t)) {
                see(e.x, e.y);
            }
            for p in points(o, t) {
                see(p[0], p[1]);
            }
            if let Some(d) = detection(o, t) {
                see(d.x, d.y);
            }
        }
    }
    let lo = |v: &[f64]| v.iter().copied().fold(f64::INFINITY, f64::min) - MARGIN;
    let hi = |v: &[f64]| v.iter().copied().fold(f64::NEG_INFINITY, f64::max) + MARGIN;
    let (mut x0, mut x1, mut y0, mut y1) = (lo(&xs), hi(&xs), lo(&ys), hi(&ys));
    // Equal scale: widen the narrow axis so the plot area is between 0.6 and 1.2 as tall as wide.
    let plot_w = (WIDTH_PX - FRAME_PX.0) as f64;
    let aspect = ((y1 - y0) / (x1 - x0)).clamp(0.6, 1.2);
    let plot_h = plot_w * aspect;
    let scale = ((x1 - x0) / plot_w).max((y1 - y0) / plot_h); // metres per pixel
    let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
    (x0, x1) = (cx - scale * plot_w / 2.0, cx + scale * plot_w / 2.0);
    (y0, y1) = (cy - scale * plot_h / 2.0, cy + scale * plot_h / 2.0);
    let height = plot_h as u32 + FRAME_PX.1;

    write_svg(path, (WIDTH_PX, height), |root, err| {
        let kind = if data.points().is_some() { "points" } else { "box detections" };
        let title =
            format!("Scene {}: {} objects, {} steps, {kind} — smoothed with lag {lag}", scene.id, objects.len(), steps);
        let mut chart = ChartBuilder::on(root)
            .caption(title, ("sans-serif", 20))
            .margin(12)
            .x_label_area_size(36)
            .y_label_area_size(48)
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(|e| err(&e))?;
        chart
            .configure_mesh()
            .x_desc("x (m)")
            .y_desc("y (m)")
            .light_line_style(TRANSPARENT)
            .bold_line_style(RGBColor(225, 225, 225))
            .x_label_formatter(&|v| format!("{v:.0}"))
            .y_label_formatter(&|v| format!("{v:.0}"))
            .draw()
            .map_err(|e| err(&e))?;

        // 1. True boxes (faint, every few steps; the last one stronger) and true paths.
        if truth.is_some() {
            let faint = TRUE_COLOUR.mix(0.35).stroke_width(1);
            let boxes = objects.iter().flat_map(|&o| {
                let obj = data.objects()[o];
                (0..steps)
                    .filter(move |t| t % BOX_EVERY == 0 || t + 1 == steps)
                    .filter_map(move |t| true_state(o, t).map(|s| (s, obj, t)))
                    .map(move |(s, obj, t)| {
                        let style = if t + 1 == steps { TRUE_COLOUR.stroke_width(2) } else { faint };
                        PathElement::new(rectangle(s.x, s.y, s.yaw, obj.length, obj.width), style)
                    })
            });
            chart
                .draw_series(boxes)
                .map_err(|e| err(&e))?
                .label("true box (every 3rd step; last step bold)")
                .legend(|(x, y)| Rectangle::new([(x, y - 5), (x + 18, y + 5)], TRUE_COLOUR.stroke_width(2)));
            let paths = objects.iter().map(|&o| {
                let pts: Vec<(f64, f64)> = (0..steps).filter_map(|t| true_state(o, t)).map(|s| (s.x, s.y)).collect();
                PathElement::new(pts, TRUE_COLOUR.mix(0.8).stroke_width(1))
            });
            chart
                .draw_series(paths)
                .map_err(|e| err(&e))?
                .label("true path")
                .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], TRUE_COLOUR.stroke_width(1)));
        }

        // 2. Observations.
        if data.points().is_some() {
            let dots = objects.iter().flat_map(|&o| {
                (0..steps).flat_map(move |t| {
                    points(o, t).iter().map(|p| Circle::new((p[0], p[1]), 2, OBS_COLOUR.mix(0.55).filled()))
                })
            });
            chart
                .draw_series(dots)
                .map_err(|e| err(&e))?
                .label("observed points")
                .legend(|(x, y)| Circle::new((x + 9, y), 3, OBS_COLOUR.filled()));
        } else {
            let dets = objects.iter().flat_map(|&o| {
                (0..steps).filter_map(move |t| detection(o, t)).map(|d| {
                    PathElement::new(outline(d.x, d.y, d.yaw, d.length, d.width), OBS_COLOUR.mix(0.7).stroke_width(1))
                })
            });
            chart
                .draw_series(dets)
                .map_err(|e| err(&e))?
                .label("detected box (tick: heading)")
                .legend(|(x, y)| Rectangle::new([(x, y - 5), (x + 18, y + 5)], OBS_COLOUR.stroke_width(1)));
        }

        // 3. Estimates: filtering means (light), smoothed means (bold) with the last box.
        let path_of = |rows: Option<&Vec<State>>| -> Vec<(f64, f64)> {
            rows.map(|r| r.iter().map(|s| (s.x, s.y)).collect()).unwrap_or_default()
        };
        let filtered =
            objects.iter().map(|&o| PathElement::new(path_of(tracks.filtered.get(o)), FILTER_COLOUR.stroke_width(2)));
        chart
            .draw_series(filtered)
            .map_err(|e| err(&e))?
            .label("filtering mean")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], FILTER_COLOUR.stroke_width(2)));
        let smoothed =
            objects.iter().map(|&o| PathElement::new(path_of(tracks.smoothed.get(o)), SMOOTH_COLOUR.stroke_width(2)));
        chart
            .draw_series(smoothed)
            .map_err(|e| err(&e))?
            .label(format!("smoothed mean (lag {lag})"))
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], SMOOTH_COLOUR.stroke_width(2)));
        let last_boxes = objects.iter().filter_map(|&o| {
            let s = tracks.smoothed.get(o)?.last()?;
            let obj = data.objects()[o];
            Some(PathElement::new(outline(s.x, s.y, s.yaw, obj.length, obj.width), SMOOTH_COLOUR.stroke_width(2)))
        });
        chart
            .draw_series(last_boxes)
            .map_err(|e| err(&e))?
            .label("estimated box, last step (tick: heading)")
            .legend(|(x, y)| Rectangle::new([(x, y - 5), (x + 18, y + 5)], SMOOTH_COLOUR.stroke_width(2)));

        // Object ids next to their last estimated position.
        let label_style = TextStyle::from(("sans-serif", 11).into_font())
            .color(&RGBColor(90, 90, 90))
            .pos(Pos::new(HPos::Left, VPos::Bottom));
        let labels = objects.iter().filter_map(|&o| {
            let s = tracks.smoothed.get(o)?.last()?;
            let obj = data.objects()[o];
            let off = 0.5 * obj.length.max(obj.width);
            Some(Text::new(format!("{}", obj.id), (s.x + off, s.y + off), label_style.clone()))
        });
        chart.draw_series(labels).map_err(|e| err(&e))?;

        // 4. The AV: its track, its pose at every step (faint) and at the last step.
        let av_path: Vec<(f64, f64)> = scene.av.iter().map(|p| (p.x, p.y)).collect();
        chart
            .draw_series(std::iter::once(PathElement::new(av_path, AV_COLOUR.stroke_width(2))))
            .map_err(|e| err(&e))?
            .label("AV track; AV at the last step")
            .legend(|(x, y)| Rectangle::new([(x, y - 5), (x + 18, y + 5)], AV_COLOUR.filled()));
        let av_steps = scene
            .av
            .iter()
            .enumerate()
            .filter(|(t, _)| t % BOX_EVERY == 0)
            .map(|(_, p)| PathElement::new(rectangle(p.x, p.y, p.yaw, AV_LENGTH, AV_WIDTH), AV_COLOUR.mix(0.3)));
        chart.draw_series(av_steps).map_err(|e| err(&e))?;
        if let Some(p) = scene.av.last() {
            chart
                .draw_series(std::iter::once(Polygon::new(
                    corners(p.x, p.y, p.yaw, AV_LENGTH, AV_WIDTH),
                    AV_COLOUR.filled(),
                )))
                .map_err(|e| err(&e))?;
            chart
                .draw_series(std::iter::once(PathElement::new(
                    outline(p.x, p.y, p.yaw, AV_LENGTH, AV_WIDTH)[..2].to_vec(),
                    WHITE.stroke_width(2),
                )))
                .map_err(|e| err(&e))?;
        }

        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.85))
            .border_style(RGBColor(160, 160, 160))
            .label_font(("sans-serif", 13))
            .draw()
            .map_err(|e| err(&e))?;
        Ok(())
    })
}
