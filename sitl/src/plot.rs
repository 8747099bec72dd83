//! Plots as standalone SVG (no dependencies): line charts for learning curves and the
//! top-down view of a race with the gates (like the paper's Fig. 3).

use crate::referee::Trace;
use firmware_core::math::Vec3;
use firmware_core::track::{Centerline, Track};
use std::fmt::Write;

/// One line of a chart.
#[derive(Clone, Debug)]
pub struct Series {
    /// Legend label.
    pub name: String,
    /// Points (x, y); non-finite ones are skipped.
    pub points: Vec<(f64, f64)>,
}

const COLORS: [&str; 6] = [
    "#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b",
];

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// A "nice" tick step (1, 2 or 5 × 10ⁿ) for about five ticks over `span`.
fn tick_step(span: f64) -> f64 {
    if !(span.is_finite() && span > 0.0) {
        return 1.0;
    }
    let raw = span / 5.0;
    let p = 10f64.powf(raw.log10().floor());
    let m = raw / p;
    p * if m < 1.5 {
        1.0
    } else if m < 3.5 {
        2.0
    } else if m < 7.5 {
        5.0
    } else {
        10.0
    }
}

/// Charts of [`line_chart`] (640 × 400 each) laid out in a grid of `columns` columns, as
/// one SVG.
pub fn grid(charts: &[String], columns: usize) -> String {
    let columns = columns.max(1);
    let rows = charts.len().div_ceil(columns);
    let (w, h) = (640 * columns, 400 * rows);
    let mut out = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" viewBox=\"0 0 {w} {h}\">\n"
    );
    for (i, chart) in charts.iter().enumerate() {
        let (x, y) = (640 * (i % columns), 400 * (i / columns));
        // A nested <svg> element takes its position from x and y.
        out.push_str(&chart.replacen("<svg ", &format!("<svg x=\"{x}\" y=\"{y}\" "), 1));
    }
    out.push_str("</svg>\n");
    out
}

/// A line chart of `series` in a 640 × 400 SVG with axes, ticks, labels and a legend.
pub fn line_chart(title: &str, x_label: &str, y_label: &str, series: &[Series]) -> String {
    let (w, h, l, r, t, b) = (640.0, 400.0, 70.0, 20.0, 40.0, 50.0);
    let (x0, x1, y0, y1) = bounds(series);
    let sx = |x: f64| l + (x - x0) / (x1 - x0) * (w - l - r);
    let sy = |y: f64| h - b - (y - y0) / (y1 - y0) * (h - t - b);
    let mut svg = String::new();
    let _ = write!(
        svg,
        r##"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" viewBox="0 0 {w} {h}" font-family="sans-serif" font-size="12">
<rect width="100%" height="100%" fill="white"/>
<text x="{}" y="22" text-anchor="middle" font-size="15">{}</text>
<rect x="{l}" y="{t}" width="{}" height="{}" fill="none" stroke="#444"/>
"##,
        w / 2.0,
        escape(title),
        w - l - r,
        h - t - b
    );
    let step = tick_step(x1 - x0);
    let mut x = (x0 / step).ceil() * step;
    while x <= x1 + 1e-9 * step {
        let px = sx(x);
        let _ = writeln!(
            svg,
            r##"<line x1="{px:.1}" y1="{}" x2="{px:.1}" y2="{t}" stroke="#eee"/><text x="{px:.1}" y="{}" text-anchor="middle">{}</text>"##,
            h - b,
            h - b + 16.0,
            fmt_tick(x, step)
        );
        x += step;
    }
    let step = tick_step(y1 - y0);
    let mut y = (y0 / step).ceil() * step;
    while y <= y1 + 1e-9 * step {
        let py = sy(y);
        let _ = writeln!(
            svg,
            r##"<line x1="{l}" y1="{py:.1}" x2="{}" y2="{py:.1}" stroke="#eee"/><text x="{}" y="{:.1}" text-anchor="end">{}</text>"##,
            w - r,
            l - 6.0,
            py + 4.0,
            fmt_tick(y, step)
        );
        y += step;
    }
    let _ = writeln!(
        svg,
        r#"<text x="{}" y="{}" text-anchor="middle">{}</text><text transform="translate(16 {}) rotate(-90)" text-anchor="middle">{}</text>"#,
        (l + w - r) / 2.0,
        h - 12.0,
        escape(x_label),
        (t + h - b) / 2.0,
        escape(y_label)
    );
    let mut drawn: Vec<(f64, f64)> = Vec::new();
    for (i, s) in series.iter().enumerate() {
        let color = COLORS[i % COLORS.len()];
        let px: Vec<(f64, f64)> = s
            .points
            .iter()
            .filter(|(x, y)| x.is_finite() && y.is_finite())
            .map(|&(x, y)| (sx(x), sy(y)))
            .collect();
        // The segments' interiors count too: a legend must not cover a line between points.
        for pair in px.windows(2) {
            let [(ax, ay), (bx, by)] = [pair[0], pair[1]];
            let n = (((bx - ax).abs() + (by - ay).abs()) / 4.0)
                .ceil()
                .min(400.0) as usize;
            drawn.extend((0..n).map(|k| {
                let f = k as f64 / n as f64;
                (ax + f * (bx - ax), ay + f * (by - ay))
            }));
        }
        drawn.extend(px.iter().copied());
        let pts: Vec<String> = px.iter().map(|(x, y)| format!("{x:.1},{y:.1}")).collect();
        let _ = writeln!(
            svg,
            r#"<polyline points="{}" fill="none" stroke="{color}" stroke-width="1.5"/>"#,
            pts.join(" ")
        );
    }
    legend(&mut svg, series, &drawn, (w, h, l, r, t, b));
    svg + "</svg>\n"
}

/// The data's extent over every finite point, `(x0, x1, y0, y1)`, widened where it is empty
/// or flat.
fn bounds(series: &[Series]) -> (f64, f64, f64, f64) {
    let finite = series
        .iter()
        .flat_map(|s| s.points.iter())
        .filter(|(x, y)| x.is_finite() && y.is_finite());
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y) in finite {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    if x0 > x1 {
        (x0, x1, y0, y1) = (0.0, 1.0, 0.0, 1.0);
    }
    if x1 - x0 < 1e-12 {
        x1 = x0 + 1.0;
    }
    if y1 - y0 < 1e-12 {
        y0 -= 0.5;
        y1 += 0.5;
    }
    (x0, x1, y0, y1)
}

/// The legend, in the corner of the plot (`frame`: width, height and the left, right, top
/// and bottom margins) where it covers the fewest `drawn` points, on a white panel.
fn legend(
    svg: &mut String,
    series: &[Series],
    drawn: &[(f64, f64)],
    frame: (f64, f64, f64, f64, f64, f64),
) {
    let (w, h, l, r, t, b) = frame;
    let text_w = series
        .iter()
        .map(|s| s.name.chars().count())
        .max()
        .unwrap_or(0) as f64
        * 6.6;
    let (lw, lh) = (36.0 + text_w + 8.0, 16.0 * series.len() as f64 + 8.0);
    let corners = [
        (l + 4.0, t + 4.0),
        (w - r - 4.0 - lw, t + 4.0),
        (w - r - 4.0 - lw, h - b - 4.0 - lh),
        (l + 4.0, h - b - 4.0 - lh),
    ];
    let covered = |&(cx, cy): &(f64, f64)| {
        drawn
            .iter()
            .filter(|(x, y)| {
                // A line within 6 px of the panel counts as under it: it would touch.
                *x >= cx - 6.0 && *x <= cx + lw + 6.0 && *y >= cy - 6.0 && *y <= cy + lh + 6.0
            })
            .count()
    };
    let (cx, cy) = corners
        .iter()
        .copied()
        .min_by_key(covered)
        .unwrap_or(corners[0]);
    if !series.is_empty() {
        let _ = writeln!(
            svg,
            r##"<rect class="legend" x="{cx:.1}" y="{cy:.1}" width="{lw:.1}" height="{lh:.1}" fill="white" fill-opacity="0.85" stroke="#ccc"/>"##
        );
    }
    for (i, s) in series.iter().enumerate() {
        let color = COLORS[i % COLORS.len()];
        let ly = cy + 12.0 + 16.0 * i as f64;
        let _ = writeln!(
            svg,
            r#"<line x1="{:.1}" y1="{ly:.1}" x2="{:.1}" y2="{ly:.1}" stroke="{color}" stroke-width="2"/><text x="{:.1}" y="{:.1}">{}</text>"#,
            cx + 6.0,
            cx + 26.0,
            cx + 32.0,
            ly + 4.0,
            escape(&s.name)
        );
    }
}

fn fmt_tick(v: f64, step: f64) -> String {
    let digits = if step >= 1.0 {
        0
    } else {
        (-step.log10().floor()) as usize
    };
    format!("{v:.digits$}")
}

/// The top-down view (x right, y up, metres) of `trace`: the centreline, the gates as bars
/// 1.6 m wide across their direction of travel with their index, the ego's path (blue) and
/// the opponent's (magenta), broken at respawns.
pub fn top_down(track: &Track<'_>, trace: &Trace, title: &str) -> String {
    let steps = trace.ego_m.len().max(trace.opponent_m.len());
    top_down_window(track, trace, 0..steps, true, title)
}

/// [`top_down`] of the steps `window` only: the view is fitted to what was flown in the
/// window (with the whole track's gates when `whole_track`), every second of the window is
/// marked on both paths with its time, and the window's overtakes (`trace.overtakes`) with
/// a ring on the ego and "overtake" (or "sustained overtake").
pub fn top_down_window(
    track: &Track<'_>,
    trace: &Trace,
    window: core::ops::Range<usize>,
    whole_track: bool,
    title: &str,
) -> String {
    let in_window = |path: &[Vec3]| -> Vec<Vec3> {
        path.get(window.start.min(path.len())..window.end.min(path.len()))
            .unwrap_or(&[])
            .to_vec()
    };
    let (ego, opp) = (in_window(&trace.ego_m), in_window(&trace.opponent_m));
    let view = View::fit(track, &ego, &opp, whole_track);
    let mut svg = String::new();
    view.header(&mut svg, title);
    view.centreline(&mut svg, track);
    view.gates(&mut svg, track);
    let per_second = (1.0 / f64::from(trace.dt_s.max(1e-3))).round().max(1.0) as usize;
    let marked = window.len() < 20 * per_second;
    for (path, color, name) in [(&ego, "#1f5fd6", "ego"), (&opp, "#d61fb4", "opponent")] {
        if path.is_empty() {
            continue;
        }
        view.path(&mut svg, trace, &window, path, color, name);
        // Seconds along a short window's paths, so the two drones can be compared in time.
        if marked {
            view.seconds(&mut svg, trace, &window, per_second, path, color);
        }
    }
    view.overtakes(&mut svg, trace, &window);
    view.legend(&mut svg);
    svg + "</svg>\n"
}

/// The frame of a top-down view: the metres it shows and the pixels it draws them on.
struct View {
    x0: f64,
    y1: f64,
    scale: f64,
    w: f64,
    h: f64,
}

impl View {
    /// Fitted to the points of `ego` and `opp` (and the gates, for the whole track) with a
    /// 1.5 m margin.
    fn fit(track: &Track<'_>, ego: &[Vec3], opp: &[Vec3], whole_track: bool) -> Self {
        let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        let gates: Vec<Vec3> = if whole_track {
            track.gates().iter().map(|g| g.center_m).collect()
        } else {
            Vec::new()
        };
        for p in gates.iter().chain(ego).chain(opp).filter(|p| p.is_finite()) {
            x0 = x0.min(f64::from(p.x));
            x1 = x1.max(f64::from(p.x));
            y0 = y0.min(f64::from(p.y));
            y1 = y1.max(f64::from(p.y));
        }
        if x0 > x1 {
            (x0, x1, y0, y1) = (-1.0, 1.0, -1.0, 1.0);
        }
        // Far excursions (a drone leaving the track) are clipped at 30 m around the origin.
        let (x0, x1) = ((x0 - 1.5).max(-30.0), (x1 + 1.5).min(30.0));
        let (y0, y1) = ((y0 - 1.5).max(-30.0), (y1 + 1.5).min(30.0));
        let scale = 780.0 / (x1 - x0).max(y1 - y0);
        let (w, h) = ((x1 - x0) * scale, (y1 - y0) * scale + 50.0);
        Self {
            x0,
            y1,
            scale,
            w,
            h,
        }
    }

    /// The pixel of `p` (x right, y down, below the 30 px title band).
    fn px(&self, p: Vec3) -> (f64, f64) {
        (
            (f64::from(p.x) - self.x0) * self.scale,
            30.0 + (self.y1 - f64::from(p.y)) * self.scale,
        )
    }

    /// `p`'s pixel as a polyline point.
    fn point(&self, p: Vec3) -> String {
        let (x, y) = self.px(p);
        format!("{x:.1},{y:.1}")
    }

    /// The opening `<svg>`, background, title and the clipped group the drawing goes in.
    fn header(&self, svg: &mut String, title: &str) {
        let (w, h) = (self.w, self.h);
        let _ = writeln!(
            svg,
            r##"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" viewBox="0 0 {w} {h}" font-family="sans-serif" font-size="12">
<rect width="100%" height="100%" fill="white"/>
<clipPath id="view"><rect x="0" y="30" width="{w}" height="{}"/></clipPath>
<text x="{}" y="20" text-anchor="middle" font-size="15">{}</text>
<g clip-path="url(#view)">"##,
            h - 50.0,
            w / 2.0,
            escape(title)
        );
    }

    /// The track's centreline, dashed grey.
    fn centreline(&self, svg: &mut String, track: &Track<'_>) {
        let line = Centerline::new(track);
        let n = line.segments() * 64;
        let pts: Vec<String> = (0..=n)
            .map(|i| self.point(line.point(i as f32 / 64.0)))
            .collect();
        let _ = writeln!(
            svg,
            r##"<polyline points="{}" fill="none" stroke="#bbb" stroke-dasharray="4 4"/>"##,
            pts.join(" ")
        );
    }

    /// Each gate as a bar across its direction of travel, its index behind it.
    fn gates(&self, svg: &mut String, track: &Track<'_>) {
        for (k, g) in track.gates().iter().enumerate() {
            let half = track.opening_half_size_m;
            let side = g.frame.rotate(Vec3::Y);
            let side = Vec3::new(side.x, side.y, 0.0);
            let side = side.scale(half / side.norm().max(1e-6));
            let ((ax, ay), (bx, by)) = (self.px(g.center_m - side), self.px(g.center_m + side));
            let (cx, cy) = self.px(g.center_m + g.forward().scale(-1.2));
            let _ = writeln!(
                svg,
                r##"<line x1="{ax:.1}" y1="{ay:.1}" x2="{bx:.1}" y2="{by:.1}" stroke="#222" stroke-width="4"/><text x="{cx:.1}" y="{cy:.1}" text-anchor="middle" fill="#222">g{k}</text>"##
            );
        }
    }

    /// A drone's `path` over `window` as polylines broken at the window's respawns.
    fn path(
        &self,
        svg: &mut String,
        trace: &Trace,
        window: &core::ops::Range<usize>,
        path: &[Vec3],
        color: &str,
        name: &str,
    ) {
        let mut start = 0usize;
        let mut cuts: Vec<usize> = trace
            .respawns
            .iter()
            .map(|&k| k as usize)
            .filter(|k| window.contains(k))
            .map(|k| k - window.start)
            .collect();
        cuts.push(path.len());
        for end in cuts {
            let seg: Vec<String> = path
                .get(start..end.min(path.len()))
                .unwrap_or(&[])
                .iter()
                .filter(|p| p.is_finite())
                .map(|&p| self.point(p))
                .collect();
            if seg.len() > 1 {
                let _ = writeln!(
                    svg,
                    r#"<polyline points="{}" fill="none" stroke="{color}" stroke-width="1.5" opacity="0.8"><title>{name}</title></polyline>"#,
                    seg.join(" ")
                );
            }
            start = end;
        }
    }

    /// A dot with its time at every whole second along a drone's `path` over `window`.
    fn seconds(
        &self,
        svg: &mut String,
        trace: &Trace,
        window: &core::ops::Range<usize>,
        per_second: usize,
        path: &[Vec3],
        color: &str,
    ) {
        for (i, p) in path
            .iter()
            .enumerate()
            .filter(|(i, p)| (window.start + i + 1).is_multiple_of(per_second) && p.is_finite())
        {
            let (x, y) = self.px(*p);
            let t = (window.start + i + 1) as f64 * f64::from(trace.dt_s);
            let _ = writeln!(
                svg,
                r##"<circle cx="{x:.1}" cy="{y:.1}" r="3" fill="{color}"/><text x="{:.1}" y="{:.1}" fill="{color}" font-size="10">{t:.0} s</text>"##,
                x + 4.0,
                y - 4.0
            );
        }
    }

    /// A ring on the ego at each of the window's overtakes, labelled with its time.
    fn overtakes(&self, svg: &mut String, trace: &Trace, window: &core::ops::Range<usize>) {
        for mark in trace
            .overtakes
            .iter()
            .filter(|m| window.contains(&(m.step as usize)))
        {
            let Some(p) = trace.ego_m.get((mark.step as usize).saturating_sub(1)) else {
                continue;
            };
            let (x, y) = self.px(*p);
            let label = if mark.sustained {
                "sustained overtake"
            } else {
                "overtake"
            };
            let t = f64::from(mark.step) * f64::from(trace.dt_s);
            let _ = writeln!(
                svg,
                r##"<circle cx="{x:.1}" cy="{y:.1}" r="8" fill="none" stroke="#e07000" stroke-width="2.5"/><text x="{:.1}" y="{:.1}" fill="#e07000" font-weight="bold">{label} at {t:.2} s</text>"##,
                x + 10.0,
                y + 14.0
            );
        }
    }

    /// Closes the drawing's group; the legend and the scale below it.
    fn legend(&self, svg: &mut String) {
        let (w, h, scale) = (self.w, self.h, self.scale);
        let _ = writeln!(
            svg,
            r##"</g><text x="10" y="{}" fill="#1f5fd6">ego</text><text x="45" y="{}" fill="#d61fb4">opponent</text><text x="{}" y="{}" text-anchor="end" fill="#666">1 m = {scale:.1} px</text>"##,
            h - 10.0,
            h - 10.0,
            w - 10.0,
            h - 10.0
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_are_round() {
        assert_eq!(tick_step(10.0), 2.0);
        assert_eq!(tick_step(1000.0), 200.0);
        assert!((tick_step(0.3) - 0.05).abs() < 1e-12);
    }

    #[test]
    fn a_chart_holds_every_series_and_survives_empty_and_nan_input() {
        let s = line_chart(
            "reward <per> iteration",
            "iteration",
            "mean reward",
            &[
                Series {
                    name: "total".into(),
                    points: vec![(0.0, 1.0), (1.0, f64::NAN), (2.0, 3.0)],
                },
                Series {
                    name: "pass".into(),
                    points: vec![],
                },
            ],
        );
        assert!(s.starts_with("<svg") && s.ends_with("</svg>\n"));
        assert_eq!(s.matches("<polyline").count(), 2);
        assert!(s.contains("reward &lt;per&gt; iteration"));
        assert!(!s.contains("NaN"));
        let empty = line_chart("t", "x", "y", &[]);
        assert!(empty.contains("</svg>"));
    }

    /// The legend's panel (x, y, width, height) in a chart.
    fn legend_box(svg: &str) -> [f64; 4] {
        let tag = svg.split("<rect class=\"legend\" ").nth(1).unwrap();
        let attr = |name: &str| -> f64 {
            let v = tag.split(&format!("{name}=\"")).nth(1).unwrap();
            v[..v.find('"').unwrap()].parse().unwrap()
        };
        [attr("x"), attr("y"), attr("width"), attr("height")]
    }

    /// How many of 1,000 points along each series' lines (x in [0, 100], y in [0, 1], the
    /// chart's 640 x 400 with margins 70/20/40/50) the legend's panel covers.
    fn covered(svg: &str, series: &[Series]) -> usize {
        let [x, y, lw, lh] = legend_box(svg);
        series
            .iter()
            .flat_map(|s| {
                s.points.windows(2).flat_map(|p| {
                    (0..100).map(move |k| {
                        let f = f64::from(k) / 100.0;
                        (
                            p[0].0 + f * (p[1].0 - p[0].0),
                            p[0].1 + f * (p[1].1 - p[0].1),
                        )
                    })
                })
            })
            .filter(|(px, py)| {
                let (sx, sy) = (70.0 + px / 100.0 * 550.0, 350.0 - py * 310.0);
                sx >= x && sx <= x + lw && sy >= y && sy <= y + lh
            })
            .count()
    }

    #[test]
    fn the_legend_avoids_the_data() {
        let curve = |name: &str, f: &dyn Fn(f64) -> f64| Series {
            name: name.into(),
            points: (0..=10)
                .map(|i| (f64::from(i) * 10.0, f(f64::from(i) * 10.0)))
                .collect(),
        };
        // A learning curve (rising, then flat at the top), a loss (falling), and two lines
        // along the top and the left edge, which leave only the bottom right free.
        let cases = [
            vec![curve("a rather long run label (seed 1)", &|x| {
                (x / 30.0).min(1.0)
            })],
            vec![curve("loss", &|x| 1.0 / (1.0 + x))],
            vec![
                curve("top", &|_| 1.0),
                Series {
                    name: "left edge".into(),
                    points: vec![(0.0, 1.0), (10.0, 0.0)],
                },
            ],
        ];
        for series in &cases {
            let svg = line_chart("t", "x", "y", series);
            assert_eq!(covered(&svg, series), 0, "{:?}", legend_box(&svg));
        }
        // The old fixed place, the top left, covered the learning curve's rise.
        let [x, y, ..] = legend_box(&line_chart("t", "x", "y", &cases[0]));
        assert!(x > 320.0 && y > 200.0, "legend at ({x}, {y})");
        let [x, y, ..] = legend_box(&line_chart("t", "x", "y", &cases[2]));
        assert!(
            x > 320.0 && y > 200.0,
            "legend at ({x}, {y}): not the free corner"
        );
    }
}
