//! The command-line tool's PNG figures (plotters, bitmap backend): panels of time series and
//! bar charts for the studies and commands, a capture or a telemetry recording
//! ([`capture`]), and the identification figure (measured against model loops on the held-out
//! part, and the model error over the whole record).
//!
//! Text is drawn with DejaVu Sans Mono, embedded in the binary (`assets/`, Bitstream Vera
//! licence, which allows redistribution), so the figure renders without system fonts.

use plotters::prelude::*;
use std::path::Path;
use std::sync::Once;
use twinstack_link::capture::Recording;

/// The embedded font.
const FONT: &[u8] = include_bytes!("../assets/DejaVuSansMono.ttf");
/// Family name the font is registered under.
const FAMILY: &str = "twinstack-mono";

/// What the figure shows.
#[derive(Clone, Copy, Debug)]
pub struct IdentificationFigure<'a> {
    /// Title line.
    pub title: &'a str,
    /// Time, s.
    pub t: &'a [f64],
    /// Drive, V.
    pub u: &'a [f64],
    /// Measured output.
    pub measured: &'a [f64],
    /// Model output (fixed-point predict).
    pub model: &'a [f64],
    /// First held-out sample.
    pub held_out_from: usize,
    /// First fitted sample.
    pub fit_from: usize,
    /// Unit of the output, for the axis labels.
    pub output_unit: &'a str,
}

/// Why the figure could not be drawn.
#[derive(Debug, thiserror::Error)]
#[error("cannot draw {path}: {message}")]
pub struct PlotError {
    path: String,
    message: String,
}

fn register_font() -> Result<(), String> {
    static ONCE: Once = Once::new();
    let mut result = Ok(());
    ONCE.call_once(|| {
        result = plotters::style::register_font(FAMILY, FontStyle::Normal, FONT)
            .map_err(|_| "embedded font is invalid".to_string());
    });
    result
}

fn bounds(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| {
            (l.min(v), h.max(v))
        });
    if !(lo.is_finite() && hi.is_finite()) {
        return (-1.0, 1.0);
    }
    let pad = 0.05 * (hi - lo).max(1e-9);
    (lo - pad, hi + pad)
}

/// Draws `fig` into the PNG `path` (1200 × 1000 px).
pub fn draw(path: &Path, fig: &IdentificationFigure) -> Result<(), PlotError> {
    let err = |m: String| PlotError {
        path: path.display().to_string(),
        message: m,
    };
    register_font().map_err(err)?;
    let e = |x: &dyn std::fmt::Display| err(x.to_string());
    let root = BitMapBackend::new(path, (1200, 1000)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(&x))?;
    let root = root.titled(fig.title, (FAMILY, 22)).map_err(|x| e(&x))?;
    let (top, bottom) = root.split_vertically(560);
    let panels = top.split_evenly((1, 2));
    let n = fig.t.len();
    let ranges = [
        (fig.fit_from, fig.held_out_from, "fitted part"),
        (fig.held_out_from, n, "held-out part"),
    ];
    for (area, &(from, to, label)) in panels.iter().zip(ranges.iter()) {
        let (ulo, uhi) = bounds(fig.u[from..to].iter().copied());
        let (ylo, yhi) = bounds(
            fig.measured[from..to]
                .iter()
                .chain(fig.model[from..to].iter())
                .copied(),
        );
        let mut chart = ChartBuilder::on(area)
            .caption(format!("loops, {label}"), (FAMILY, 18))
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(ulo..uhi, ylo..yhi)
            .map_err(|x| e(&x))?;
        chart
            .configure_mesh()
            .x_desc("drive u [V]")
            .y_desc(format!("output x [{}]", fig.output_unit))
            .label_style((FAMILY, 14))
            .draw()
            .map_err(|x| e(&x))?;
        chart
            .draw_series(LineSeries::new(
                (from..to).map(|k| (fig.u[k], fig.measured[k])),
                BLUE.stroke_width(2),
            ))
            .map_err(|x| e(&x))?
            .label("measured")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLUE.stroke_width(2)));
        chart
            .draw_series(LineSeries::new(
                (from..to).map(|k| (fig.u[k], fig.model[k])),
                RED.stroke_width(1),
            ))
            .map_err(|x| e(&x))?
            .label("model (fixed point)")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED));
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperLeft)
            .label_font((FAMILY, 14))
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|x| e(&x))?;
    }

    let error: Vec<f64> = (0..n).map(|k| fig.model[k] - fig.measured[k]).collect();
    let (tlo, thi) = (fig.t[0], fig.t[n - 1]);
    let (elo, ehi) = bounds(error[fig.fit_from..].iter().copied());
    let mut chart = ChartBuilder::on(&bottom)
        .caption(
            "error = model - measured (grey: before the fit window; the line marks --fit-until)",
            (FAMILY, 18),
        )
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(tlo..thi, elo..ehi)
        .map_err(|x| e(&x))?;
    chart
        .configure_mesh()
        .x_desc("time t [s]")
        .y_desc(format!("error [{}]", fig.output_unit))
        .label_style((FAMILY, 14))
        .draw()
        .map_err(|x| e(&x))?;
    chart
        .draw_series(LineSeries::new(
            (0..fig.fit_from).map(|k| (fig.t[k], error[k].clamp(elo, ehi))),
            RGBColor(160, 160, 160),
        ))
        .map_err(|x| e(&x))?;
    chart
        .draw_series(LineSeries::new(
            (fig.fit_from..n).map(|k| (fig.t[k], error[k])),
            RED,
        ))
        .map_err(|x| e(&x))?;
    let split = fig.t[fig.held_out_from.min(n - 1)];
    chart
        .draw_series(LineSeries::new(
            vec![(split, elo), (split, ehi)],
            BLACK.stroke_width(2),
        ))
        .map_err(|x| e(&x))?;
    root.present().map_err(|x| e(&x))?;
    Ok(())
}

/// One line of a [`Panel`].
#[derive(Clone, Debug)]
pub struct Series {
    /// Legend text.
    pub label: String,
    /// Points `(x, y)`.
    pub points: Vec<(f64, f64)>,
    /// Colour.
    pub color: RGBColor,
}

/// One chart of a figure.
#[derive(Clone, Debug)]
pub struct Panel {
    /// Caption above the chart.
    pub caption: String,
    /// X axis label.
    pub x_label: String,
    /// Y axis label.
    pub y_label: String,
    /// The lines.
    pub series: Vec<Series>,
}

/// One bar of a [`BarPanel`].
#[derive(Clone, Debug)]
pub struct Bar {
    /// The row's label, left of the axis.
    pub label: String,
    /// The bar's length, in the x axis' unit.
    pub value: f64,
    /// Text after the value at the bar's end (`""` for none).
    pub note: String,
    /// Colour.
    pub color: RGBColor,
}

/// A horizontal bar chart: one row per bar, the first at the top, each labelled left of the
/// axis with its value written at the bar's end, so no legend covers the bars.
#[derive(Clone, Debug)]
pub struct BarPanel {
    /// Caption above the chart.
    pub caption: String,
    /// X axis label (the bars' unit).
    pub x_label: String,
    /// The bars, top to bottom.
    pub bars: Vec<Bar>,
}

/// One chart of a figure: lines or bars.
#[derive(Clone, Copy, Debug)]
pub enum Chart<'a> {
    /// Lines with a legend.
    Lines(&'a Panel),
    /// A horizontal bar chart.
    Bars(&'a BarPanel),
}

/// Draws `panels` side by side, `columns` to a row, into the PNG `path`.
pub fn draw_panels(
    path: &Path,
    title: &str,
    panels: &[Panel],
    columns: usize,
) -> Result<(), PlotError> {
    let charts: Vec<Chart> = panels.iter().map(Chart::Lines).collect();
    draw_charts(path, title, &charts, columns)
}

/// Draws `charts` (lines or bars) side by side, `columns` to a row, into the PNG `path`.
pub fn draw_charts(
    path: &Path,
    title: &str,
    charts: &[Chart],
    columns: usize,
) -> Result<(), PlotError> {
    let err = |m: String| PlotError {
        path: path.display().to_string(),
        message: m,
    };
    register_font().map_err(err)?;
    let e = |x: &dyn std::fmt::Display| err(x.to_string());
    let columns = columns.max(1);
    let rows = charts.len().div_ceil(columns).max(1);
    let root = BitMapBackend::new(path, (600 * columns as u32, 480 * rows as u32 + 40))
        .into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(&x))?;
    let root = root.titled(title, (FAMILY, 22)).map_err(|x| e(&x))?;
    for (area, chart) in root.split_evenly((rows, columns)).iter().zip(charts) {
        match chart {
            Chart::Lines(panel) => draw_lines(area, panel).map_err(|x| e(&x))?,
            Chart::Bars(panel) => draw_bars(area, panel).map_err(|x| e(&x))?,
        }
    }
    root.present().map_err(|x| e(&x))?;
    Ok(())
}

type Area<'a> = DrawingArea<BitMapBackend<'a>, plotters::coord::Shift>;
type DrawResult<'a> =
    Result<(), DrawingAreaErrorKind<<BitMapBackend<'a> as DrawingBackend>::ErrorType>>;

fn draw_lines<'a>(area: &Area<'a>, panel: &Panel) -> DrawResult<'a> {
    let (xlo, xhi) = bounds(
        panel
            .series
            .iter()
            .flat_map(|s| s.points.iter().map(|p| p.0)),
    );
    let (ylo, yhi) = bounds(
        panel
            .series
            .iter()
            .flat_map(|s| s.points.iter().map(|p| p.1)),
    );
    let mut chart = ChartBuilder::on(area)
        .caption(&panel.caption, (FAMILY, 18))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(xlo..xhi, ylo..yhi)?;
    chart
        .configure_mesh()
        .x_desc(&panel.x_label)
        .y_desc(&panel.y_label)
        .label_style((FAMILY, 14))
        .draw()?;
    for s in &panel.series {
        let color = s.color;
        chart
            .draw_series(LineSeries::new(
                s.points.iter().copied(),
                color.stroke_width(2),
            ))?
            .label(&s.label)
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
            });
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .label_font((FAMILY, 14))
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()?;
    Ok(())
}

fn draw_bars<'a>(area: &Area<'a>, panel: &BarPanel) -> DrawResult<'a> {
    use plotters::style::text_anchor::{HPos, Pos, VPos};
    let n = panel.bars.len().max(1);
    let top = panel
        .bars
        .iter()
        .map(|b| b.value)
        .filter(|v| v.is_finite())
        .fold(0.0, f64::max);
    // Room right of the longest bar for its value.
    let xmax = if top > 0.0 { top * 1.25 } else { 1.0 };
    // Row r (from the bottom) holds bar n - 1 - r: the first bar at the top. Each row: its
    // label on top, left-aligned over the axis, the bar under it, the value at the bar's end.
    let mut chart = ChartBuilder::on(area)
        .caption(&panel.caption, (FAMILY, 18))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(12)
        .build_cartesian_2d(0f64..xmax, 0f64..n as f64)?;
    chart
        .configure_mesh()
        .disable_y_mesh()
        .y_labels(0)
        .x_desc(&panel.x_label)
        .label_style((FAMILY, 14))
        .draw()?;
    let rows: Vec<(f64, &Bar)> = panel
        .bars
        .iter()
        .enumerate()
        .map(|(i, b)| ((n - 1 - i) as f64, b))
        .collect();
    chart.draw_series(
        rows.iter()
            .filter(|(_, b)| b.value.is_finite())
            .map(|(r, b)| {
                Rectangle::new(
                    [(0.0, r + 0.12), (b.value.max(0.0), r + 0.52)],
                    b.color.filled(),
                )
            }),
    )?;
    let style = |h| {
        TextStyle::from((FAMILY, 14).into_font())
            .color(&BLACK)
            .pos(Pos::new(h, VPos::Center))
    };
    chart.draw_series(
        rows.iter()
            .map(|(r, b)| Text::new(b.label.clone(), (0.0, r + 0.76), style(HPos::Left))),
    )?;
    chart.draw_series(rows.iter().map(|(r, b)| {
        let (at, text) = if b.value.is_finite() {
            (b.value.max(0.0), format!(" {:.2} {}", b.value, b.note))
        } else {
            (0.0, b.note.clone())
        };
        Text::new(
            text.trim_end().to_string(),
            (at, r + 0.32),
            style(HPos::Left),
        )
    }))?;
    Ok(())
}

/// Draws a capture or a telemetry recording into the PNG `path`: one panel for the displacements (µm), one for
/// the stack voltages, against time.
pub fn capture(recording: &Recording, path: &Path, title: &str) -> Result<(), PlotError> {
    let colors = [
        RGBColor(0, 0, 0),
        RGBColor(31, 119, 180),
        RGBColor(214, 39, 40),
        RGBColor(44, 160, 44),
        RGBColor(255, 127, 14),
        RGBColor(148, 103, 189),
    ];
    let mut panels = Vec::new();
    for (caption, unit) in [("displacement", "um"), ("stack voltages", "V")] {
        let series: Vec<Series> = recording
            .columns
            .iter()
            .filter(|c| c.unit == unit)
            .map(|c| Series {
                label: c.channel.name().to_string(),
                points: recording
                    .t
                    .iter()
                    .copied()
                    .zip(c.values.iter().copied())
                    .collect(),
                color: colors[c.channel as usize % colors.len()],
            })
            .collect();
        if !series.is_empty() {
            panels.push(Panel {
                caption: caption.to_string(),
                x_label: "t from the trigger [s]".to_string(),
                y_label: format!("[{unit}]"),
                series,
            });
        }
    }
    draw_panels(path, title, &panels, 1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_figure_renders_to_a_png_with_the_embedded_font() {
        let t: Vec<f64> = (0..400).map(|k| k as f64 * 0.01).collect();
        let u: Vec<f64> = t.iter().map(|&t| 100.0 * (t * 3.0).sin()).collect();
        let measured: Vec<f64> = u.iter().map(|&v| 0.1 * v + 0.3).collect();
        let model: Vec<f64> = u.iter().map(|&v| 0.1 * v).collect();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("figure.png");
        let fig = IdentificationFigure {
            title: "test",
            t: &t,
            u: &u,
            measured: &measured,
            model: &model,
            held_out_from: 300,
            fit_from: 10,
            output_unit: "um",
        };
        draw(&path, &fig).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
        assert!(
            bytes.len() > 10_000,
            "a figure with axes and text, not an empty image"
        );
    }
}
