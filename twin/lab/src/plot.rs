//! PNG line plots of experiments (plotters' bitmap backend). Text needs a
//! TrueType font: plotters' `ab_glyph` renders it without system font
//! libraries, from a font file read once at run time.

use plotters::prelude::*;
use plotters::style::FontStyle;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// Where a font is looked for, after the `TWIN_FONT` environment variable:
/// DejaVu Sans (Debian/Ubuntu `fonts-dejavu-core`, Fedora, Arch), then the
/// usual Arial of macOS and Windows.
const FONT_PATHS: [&str; 6] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu-sans-fonts/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/Library/Fonts/Arial.ttf",
    "C:\\Windows\\Fonts\\arial.ttf",
];

/// Why a plot could not be drawn.
#[derive(Debug, Clone, thiserror::Error)]
pub enum PlotError {
    /// No font to label it with, or one that is not a font: what to do.
    #[error("{0}")]
    Font(String),
    /// plotters failed to draw or to write the file, in its own words.
    #[error("cannot draw {}: {why}", path.display())]
    Draw { path: PathBuf, why: String },
    /// A picture's size that cannot hold what it must show: the range.
    #[error("{0}")]
    Size(String),
}

static FONT: OnceLock<Result<(), String>> = OnceLock::new();

/// Register a font for plotters once per process.
pub(crate) fn ensure_font() -> Result<(), PlotError> {
    FONT.get_or_init(|| {
        let env = std::env::var("TWIN_FONT").ok();
        let candidates = env.iter().map(String::as_str).chain(FONT_PATHS);
        for path in candidates {
            if let Ok(bytes) = std::fs::read(path) {
                // plotters keeps fonts for the process's lifetime.
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                return plotters::style::register_font("sans-serif", FontStyle::Normal, bytes)
                    .map_err(|_| {
                        format!("{path} is not a TrueType font: point TWIN_FONT at a .ttf file")
                    });
            }
        }
        Err(format!(
            "no font to label the plot with: install DejaVu Sans (Debian: apt-get install \
             fonts-dejavu-core) or point TWIN_FONT at a .ttf file (looked in {})",
            FONT_PATHS.join(", ")
        ))
    })
    .clone()
    .map_err(PlotError::Font)
}

/// One line on a plot.
#[derive(Debug, Clone)]
pub struct Series<'a> {
    pub name: &'a str,
    pub color: RGBColor,
    pub points: Vec<(f64, f64)>,
    /// Draw the samples as dots as well.
    pub dots: bool,
    pub width: u32,
}

/// Axis labels and ranges.
#[derive(Debug, Clone)]
pub struct Axes<'a> {
    pub title: &'a str,
    pub x_label: &'a str,
    pub y_label: &'a str,
    pub x_range: (f64, f64),
    pub y_range: (f64, f64),
    /// Legend in the upper left rather than the lower right.
    pub legend_upper_left: bool,
}

pub const SET_POINT: RGBColor = RGBColor(120, 120, 120);
pub const WHEEL: RGBColor = RGBColor(20, 20, 20);
pub const MOTOR: RGBColor = RGBColor(31, 119, 180);
pub const LIGHT: RGBColor = RGBColor(214, 39, 40);
pub const EXTRA: RGBColor = RGBColor(44, 160, 44);

/// Draw `series` to a `width × height` PNG at `path`.
pub fn line_plot(
    path: &Path,
    axes: &Axes,
    series: &[Series],
    size: (u32, u32),
) -> Result<(), PlotError> {
    ensure_font()?;
    let draw = || -> Result<(), Box<dyn std::error::Error>> {
        let root = BitMapBackend::new(path, size).into_drawing_area();
        root.fill(&WHITE)?;
        let (x0, x1) = axes.x_range;
        let (y0, y1) = axes.y_range;
        let mut chart = ChartBuilder::on(&root)
            .caption(axes.title, ("sans-serif", 22))
            .margin(12)
            .margin_right(28)
            .x_label_area_size(42)
            .y_label_area_size(64)
            .build_cartesian_2d(x0..x1, y0..y1)?;
        chart
            .configure_mesh()
            .x_desc(axes.x_label)
            .y_desc(axes.y_label)
            .label_style(("sans-serif", 15))
            .x_label_formatter(&|v| tick(*v))
            .y_label_formatter(&|v| tick(*v))
            .light_line_style(RGBColor(235, 235, 235))
            .draw()?;
        for s in series {
            let style = s.color.stroke_width(s.width);
            let color = s.color;
            let drawn = chart.draw_series(LineSeries::new(s.points.iter().copied(), style))?;
            if !s.name.is_empty() {
                drawn.label(s.name).legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
                });
            }
            if s.dots {
                chart.draw_series(
                    s.points
                        .iter()
                        .map(|&p| Circle::new(p, 3, s.color.filled())),
                )?;
            }
        }
        chart
            .configure_series_labels()
            .position(if axes.legend_upper_left {
                SeriesLabelPosition::UpperLeft
            } else {
                SeriesLabelPosition::LowerRight
            })
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 15))
            .draw()?;
        root.present()?;
        Ok(())
    };
    draw().map_err(|e| PlotError::Draw {
        path: path.to_path_buf(),
        why: e.to_string(),
    })
}

/// A range that holds every point of `series` with a margin, never empty.
pub fn fit_range(values: impl Iterator<Item = f64>, margin: f64) -> (f64, f64) {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v), b.max(v))
        });
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    let pad = ((hi - lo) * margin).max(1e-9);
    (lo - pad, hi + pad)
}

/// A tick label with no more decimals than it needs.
fn tick(v: f64) -> String {
    if (v - v.round()).abs() < 1e-9 {
        format!("{v:.0}")
    } else {
        let s = format!("{v:.2}");
        s.trim_end_matches('0').to_string()
    }
}
