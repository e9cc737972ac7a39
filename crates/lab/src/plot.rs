//! Charts drawn with plotters need a font; Tessera ships DejaVu Sans (Bitstream Vera licence,
//! `assets/DejaVuSans-LICENSE.txt`) so that plots look the same on every machine.

static DEJAVU_SANS: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

/// Registers the shipped font as "sans-serif" (once; later calls do nothing).
pub fn register_font() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let _ = plotters::style::register_font("sans-serif", plotters::style::FontStyle::Normal, DEJAVU_SANS);
    });
}

/// One line of a chart: its legend label and its (x, y) points.
pub struct Series {
    pub label: String,
    pub points: Vec<(f64, f64)>,
}

/// Distinct line colours, cycled.
const COLOURS: [(u8, u8, u8); 10] = [
    (200, 30, 30),
    (30, 60, 200),
    (20, 140, 40),
    (230, 130, 0),
    (130, 40, 170),
    (0, 150, 160),
    (120, 80, 30),
    (220, 60, 150),
    (90, 90, 90),
    (150, 170, 0),
];

/// A log-log line chart with points marked, one line per series, written as a PNG.
pub fn log_log(
    path: &std::path::Path,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    series: &[Series],
) -> anyhow::Result<()> {
    log_log_panels(path, &[(title.to_string(), series)], x_desc, y_desc)
}

/// Log-log line charts side by side in one PNG, one panel per `(title, series)`.
pub fn log_log_panels(
    path: &std::path::Path,
    panels: &[(String, &[Series])],
    x_desc: &str,
    y_desc: &str,
) -> anyhow::Result<()> {
    use plotters::prelude::*;
    register_font();
    let root = BitMapBackend::new(path, (900 * panels.len().max(1) as u32, 600)).into_drawing_area();
    let draw = || -> std::result::Result<(), Box<dyn std::error::Error>> {
        root.fill(&WHITE)?;
        for (area, (title, series)) in root.split_evenly((1, panels.len().max(1))).iter().zip(panels) {
            panel(area, title, x_desc, y_desc, series)?;
        }
        root.present()?;
        Ok(())
    };
    draw().map_err(|e| anyhow::anyhow!("drawing {}: {e}", path.display()))
}

fn panel(
    area: &plotters::drawing::DrawingArea<plotters::prelude::BitMapBackend<'_>, plotters::coord::Shift>,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    series: &[Series],
) -> std::result::Result<(), Box<dyn std::error::Error>> {
    use plotters::prelude::*;
    let all = || series.iter().flat_map(|s| s.points.iter()).filter(|p| p.0 > 0.0 && p.1 > 0.0);
    let range =
        |f: fn(&(f64, f64)) -> f64| all().map(f).fold((f64::MAX, f64::MIN), |(lo, hi), v| (lo.min(v), hi.max(v)));
    let ((x0, x1), (y0, y1)) = (range(|p| p.0), range(|p| p.1));
    if x0 > x1 || y0 > y1 {
        // Every error 0 (or no point): a log scale has no room for it; say so in the panel.
        area.titled(&format!("{title}: nothing above 0 to plot"), ("sans-serif", 24))?;
        return Ok(());
    }
    let mut chart = ChartBuilder::on(area)
        .caption(title, ("sans-serif", 24))
        .margin(20)
        .x_label_area_size(50)
        .y_label_area_size(80)
        .build_cartesian_2d((x0 / 1.5..x1 * 1.5).log_scale(), (y0 / 2.0..y1 * 2.0).log_scale())?;
    chart
        .configure_mesh()
        .x_label_formatter(&|x| if *x >= 1.0 { format!("{x:.0}") } else { format!("{x:.2}") })
        .y_label_formatter(&|y| format!("{y:.0e}"))
        .x_desc(x_desc)
        .y_desc(y_desc)
        .draw()?;
    for (i, s) in series.iter().enumerate() {
        let (r, g, b) = COLOURS[i % COLOURS.len()];
        let colour = RGBColor(r, g, b);
        let pts: Vec<(f64, f64)> = s.points.iter().copied().filter(|p| p.0 > 0.0 && p.1 > 0.0).collect();
        chart
            .draw_series(LineSeries::new(pts.clone(), colour.stroke_width(2)))?
            .label(s.label.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2)));
        chart.draw_series(pts.iter().map(|&p| Circle::new(p, 3, colour.filled())))?;
    }
    // Error curves fall to the right: the lower left is free for the legend.
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerLeft)
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()?;
    Ok(())
}
