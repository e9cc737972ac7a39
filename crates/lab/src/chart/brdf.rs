//! `tessera chart brdf`: directional albedo over view angle and roughness of Dimov, Gurov and Penzov's BRDF as
//! printed and of the normalised Cook-Torrance form Tessera renders, for a dielectric (n = 1.5,
//! over a white base in the normalised form) and for gold at 550 nm. Albedo above 1 means the
//! surface reflects more than it receives, and a scene of it has q >= 1: the Neumann series, and
//! with it the collision estimator and `k_eps`, stop converging.

use crate::chart::BrdfArgs;
use anyhow::{Context, Result};
use std::io::Write;
use tessera_render::bsdf::printed::{self, Interface};
use tessera_render::spectral::data;

/// View angles (degrees) and roughnesses (Beckmann m = alpha) of the maps.
pub const THETAS: [f32; 19] =
    [0., 5., 10., 15., 20., 25., 30., 35., 40., 45., 50., 55., 60., 65., 70., 75., 80., 85., 89.];
pub const ROUGHNESS: [f32; 10] = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0];

/// The two materials: name and interface.
pub fn materials() -> [(&'static str, Interface); 2] {
    let (n, k) = data::metal("Au").map_or((0.43, 2.45), |(n, k)| (n.eval(550.0) as f32, k.eval(550.0) as f32));
    [("dielectric n=1.5", Interface::Dielectric { eta: 1.5 }), ("gold at 550 nm", Interface::Conductor { n, k })]
}

/// One albedo of the maps.
pub struct Cell {
    pub form: &'static str,
    pub material: &'static str,
    pub theta: f32,
    pub roughness: f32,
    pub albedo: f64,
}

/// Every cell of both forms and materials, at quadrature `resolution`.
pub fn cells(resolution: usize) -> Vec<Cell> {
    let mut out = Vec::new();
    for (material, interface) in materials() {
        for &roughness in &ROUGHNESS {
            let bsdf = printed::normalised(interface, roughness);
            for &theta in &THETAS {
                let t = theta.to_radians();
                let p = printed::albedo(|wo, wi| printed::eval(interface, roughness, wo, wi), t, resolution);
                let n = printed::albedo(|wo, wi| bsdf.eval(wo, wi).x, t, resolution);
                out.push(Cell { form: "printed", material, theta, roughness, albedo: p });
                out.push(Cell { form: "normalised", material, theta, roughness, albedo: n });
            }
        }
    }
    out
}

pub fn brdf(args: BrdfArgs) -> Result<()> {
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let cells = cells(args.resolution as usize);
    let csv = args.out.join("brdf-albedo.csv");
    let mut f =
        std::io::BufWriter::new(std::fs::File::create(&csv).with_context(|| format!("creating {}", csv.display()))?);
    writeln!(f, "form,material,theta_deg,roughness,albedo")?;
    for c in &cells {
        writeln!(f, "{},{},{},{},{:.6}", c.form, c.material, c.theta, c.roughness, c.albedo)?;
    }
    f.flush()?;
    for form in ["printed", "normalised"] {
        for (material, _) in materials() {
            let of = || cells.iter().filter(|c| c.form == form && c.material == material);
            let above = of().filter(|c| c.albedo > 1.0).count();
            let max = of().map(|c| c.albedo).fold(0.0, f64::max);
            println!("{form:<10} {material:<17} max albedo {max:.3}; above 1 in {above} of {} cells", of().count());
        }
    }
    heat_maps(&cells, &args.out.join("brdf-albedo.png"))?;
    eprintln!("wrote brdf-albedo.csv and brdf-albedo.png in {}", args.out.display());
    Ok(())
}

/// Blue (0) to white (1) for albedo up to 1; red, deepening to 2, above.
fn colour(a: f64) -> plotters::style::RGBColor {
    if a <= 1.0 {
        let t = a.clamp(0.0, 1.0);
        plotters::style::RGBColor((40.0 + 215.0 * t) as u8, (60.0 + 195.0 * t) as u8, 255)
    } else {
        let t = ((a - 1.0).min(1.0) * 200.0) as u8;
        plotters::style::RGBColor(255, 200 - t, 200 - t)
    }
}

fn heat_maps(cells: &[Cell], path: &std::path::Path) -> Result<()> {
    use plotters::prelude::*;
    crate::plot::register_font();
    let root = BitMapBackend::new(path, (1200, 900)).into_drawing_area();
    let draw = || -> std::result::Result<(), Box<dyn std::error::Error>> {
        root.fill(&WHITE)?;
        let (title, body) = root.split_vertically(50);
        title.titled(
            "Directional albedo (blue 0 .. white 1; red: above 1, reflects more than it receives)",
            ("sans-serif", 22),
        )?;
        let panels = body.split_evenly((2, 2));
        let mut i = 0;
        for form in ["printed", "normalised"] {
            for (material, _) in materials() {
                let mut chart = ChartBuilder::on(&panels[i])
                    .caption(format!("{form}: {material}"), ("sans-serif", 18))
                    .margin(10)
                    .x_label_area_size(35)
                    .y_label_area_size(45)
                    .build_cartesian_2d(0f32..90f32, 0.05f32..1.05f32)?;
                chart.configure_mesh().x_desc("view angle (degrees)").y_desc("roughness m").disable_mesh().draw()?;
                let half_theta = 2.5;
                chart.draw_series(cells.iter().filter(|c| c.form == form && c.material == material).map(|c| {
                    let (x0, x1) = ((c.theta - half_theta).max(0.0), (c.theta + half_theta).min(90.0));
                    Rectangle::new([(x0, c.roughness - 0.05), (x1, c.roughness + 0.05)], colour(c.albedo).filled())
                }))?;
                i += 1;
            }
        }
        root.present()?;
        Ok(())
    };
    draw().map_err(|e| anyhow::anyhow!("drawing {}: {e}", path.display()))
}
