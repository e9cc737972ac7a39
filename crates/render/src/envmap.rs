//! An environment map: an equirectangular image of the radiance arriving from every direction,
//! seen as the background and lighting the scene. Oriented as Mitsuba 3's `envmap` emitter with
//! an identity transform: +Y is up, the image's centre column faces +Z, its left edge -Z and its
//! first quarter +X; `rotation` turns it about +Y. Each texel is a cell of constant radiance
//! (nearest-texel lookup), and light sampling picks cells in proportion to their radiance times
//! the solid angle they cover (luminance x sin(theta)), then a point inside the cell uniformly:
//! the density is exactly proportional to the map's luminance, and positive wherever the map
//! shines.

use glam::Vec3;
use libm::{acosf as acos, atan2f as atan2, cosf as cos, sinf as sin};
use std::f32::consts::PI;

/// Most texels a map may have (as textures: 8192 x 8192).
pub const MAX_TEXELS: usize = 1 << 26;

pub struct EnvMap {
    width: usize,
    height: usize,
    /// Linear RGB radiance times the strength, row by row from the top (+Y).
    texels: Vec<Vec3>,
    /// sin and cos of the rotation about +Y.
    rotation: (f32, f32),
    /// Per row, the cumulative share of the total weight up to and including it (the last is 1).
    rows: Vec<f32>,
    /// Per texel, the cumulative share of its row's weight (each row's last is 1).
    columns: Vec<f32>,
    /// Per texel, the probability of choosing its cell.
    cell_pmf: Vec<f32>,
    /// The integral of luminance over the sphere, for the map's share of light sampling.
    luminance_integral: f32,
    /// Sample directions uniformly over the sphere instead (for comparison: `tessera bench envmap`).
    uniform: bool,
}

fn luminance(c: Vec3) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

/// A cumulative distribution from weights, normalised so that the last entry is exactly 1 (all
/// zeros give a uniform one).
fn cumulative(weights: &[f64]) -> Vec<f32> {
    let total: f64 = weights.iter().sum();
    let mut acc = 0.0f64;
    let mut out: Vec<f32> = weights
        .iter()
        .enumerate()
        .map(|(i, &w)| {
            acc += w;
            if total > 0.0 { (acc / total) as f32 } else { (i + 1) as f32 / weights.len() as f32 }
        })
        .collect();
    if let Some(last) = out.last_mut() {
        *last = 1.0;
    }
    out
}

/// The index of the interval of `cdf` holding `u`, and `u` rescaled to [0, 1) within it.
fn pick(cdf: &[f32], u: f32) -> (usize, f32) {
    let i = cdf.partition_point(|&c| c <= u).min(cdf.len() - 1);
    let lo = if i == 0 { 0.0 } else { cdf[i - 1] };
    let width = cdf[i] - lo;
    let rest = if width > 0.0 { ((u - lo) / width).clamp(0.0, 1.0 - f32::EPSILON / 2.0) } else { 0.5 };
    (i, rest)
}

impl EnvMap {
    /// A map of `width` x `height` linear RGB texels (rows from the top), scaled by `strength`
    /// and turned `rotate_degrees` about +Y. Refuses an empty or oversized image and values
    /// that are negative or not finite, naming the first.
    pub fn new(
        width: usize,
        height: usize,
        texels: &[[f32; 3]],
        strength: f32,
        rotate_degrees: f32,
    ) -> Result<EnvMap, String> {
        let n = width.checked_mul(height).filter(|&n| n > 0 && n <= MAX_TEXELS).ok_or_else(|| {
            format!("an environment map of {width} x {height} texels (at least 1, at most {MAX_TEXELS})")
        })?;
        if texels.len() != n {
            return Err(format!("{} texels for a {width} x {height} map", texels.len()));
        }
        if !(strength.is_finite() && strength >= 0.0) {
            return Err(format!("strength {strength} is not a finite number >= 0"));
        }
        if !rotate_degrees.is_finite() {
            return Err(format!("rotation {rotate_degrees} degrees is not finite"));
        }
        if let Some(i) = texels.iter().position(|t| t.iter().any(|c| !c.is_finite() || *c < 0.0)) {
            return Err(format!(
                "texel ({}, {}) is {:?}: radiance must be finite and not negative",
                i % width,
                i / width,
                texels[i]
            ));
        }
        let texels: Vec<Vec3> = texels.iter().map(|&t| Vec3::from_array(t) * strength).collect();
        // A cell's weight: its luminance times sin(theta) at its centre row, as its solid angle
        // goes. Weights are made a row at a time (twice: for the rows' sums, then for the rows'
        // own distributions), never for the whole map at once: 8 bytes a texel less at the peak.
        let row_sin: Vec<f64> = (0..height).map(|j| sin(PI * (j as f32 + 0.5) / height as f32) as f64).collect();
        let row_of = |j: usize, into: &mut Vec<f64>| {
            into.clear();
            into.extend(texels[j * width..(j + 1) * width].iter().map(|&t| luminance(t).max(0.0) as f64 * row_sin[j]));
        };
        let mut row = Vec::with_capacity(width);
        let (mut row_weights, mut total) = (Vec::with_capacity(height), 0.0f64);
        for j in 0..height {
            row_of(j, &mut row);
            row_weights.push(row.iter().sum::<f64>());
            // Summed texel by texel in order, as the whole map's weights were: the same bits.
            for &w in &row {
                total += w;
            }
        }
        let rows = cumulative(&row_weights);
        let mut columns = Vec::with_capacity(n);
        let mut cell_pmf = Vec::with_capacity(n);
        for j in 0..height {
            row_of(j, &mut row);
            columns.extend(cumulative(&row));
            if total > 0.0 {
                cell_pmf.extend(row.iter().map(|&w| (w / total) as f32));
            } else {
                cell_pmf.extend(std::iter::repeat_n(1.0 / n as f32, width));
            }
        }
        let cell_solid_angle = 2.0 * PI * PI / n as f32;
        let luminance_integral = (total * cell_solid_angle as f64) as f32;
        let radians = rotate_degrees.to_radians();
        Ok(EnvMap {
            width,
            height,
            texels,
            rotation: (sin(radians), cos(radians)),
            rows,
            columns,
            cell_pmf,
            luminance_integral,
            uniform: false,
        })
    }

    /// The same map, sampled uniformly over the sphere instead of by its luminance: what
    /// importance sampling is measured against.
    pub fn sampled_uniformly(mut self) -> EnvMap {
        self.uniform = true;
        self
    }

    /// The integral of the map's luminance over all directions (its power per unit area, times
    /// pi, of a distant sphere).
    pub fn luminance_integral(&self) -> f32 {
        self.luminance_integral
    }

    /// The largest radiance component of any texel.
    pub fn max_radiance(&self) -> f32 {
        self.texels.iter().map(|t| t.max_element()).fold(0.0, f32::max)
    }

    /// Map coordinates (u, v) in [0, 1) of world direction `d`.
    fn uv(&self, d: Vec3) -> (f32, f32) {
        let (s, c) = self.rotation;
        // Into the map's frame: the inverse rotation about +Y.
        let local = Vec3::new(c * d.x - s * d.z, d.y, s * d.x + c * d.z);
        let mut u = atan2(local.x, -local.z) / (2.0 * PI);
        if u < 0.0 {
            u += 1.0;
        }
        let v = acos(local.y.clamp(-1.0, 1.0)) / PI;
        (u.min(1.0 - f32::EPSILON / 2.0), v)
    }

    /// The world direction at map coordinates (u, v), and sin(theta) there.
    fn direction(&self, u: f32, v: f32) -> (Vec3, f32) {
        let (phi, theta) = (2.0 * PI * u, PI * v);
        let (sin_t, cos_t) = (sin(theta), cos(theta));
        let local = Vec3::new(sin(phi) * sin_t, cos_t, -cos(phi) * sin_t);
        let (s, c) = self.rotation;
        (Vec3::new(c * local.x + s * local.z, local.y, -s * local.x + c * local.z), sin_t)
    }

    fn cell(&self, d: Vec3) -> usize {
        let (u, v) = self.uv(d);
        let i = ((u * self.width as f32) as usize).min(self.width - 1);
        let j = ((v * self.height as f32) as usize).min(self.height - 1);
        j * self.width + i
    }

    /// Radiance arriving along world direction `d` (unit), from the direction `d` points to.
    pub fn radiance(&self, d: Vec3) -> Vec3 {
        self.texels[self.cell(d)]
    }

    /// Solid-angle density with which [`Self::sample`] picks direction `d`.
    pub fn pdf(&self, d: Vec3) -> f32 {
        if self.uniform {
            return 1.0 / (4.0 * PI);
        }
        let (_, v) = self.uv(d);
        let sin_t = sin(PI * v);
        if sin_t <= 0.0 {
            return 0.0;
        }
        let n = (self.width * self.height) as f32;
        self.cell_pmf[self.cell(d)] * n / (2.0 * PI * PI * sin_t)
    }

    /// A direction drawn with density [`Self::pdf`], from two uniform numbers; its radiance and
    /// density. `None` where the density vanishes (the poles).
    pub fn sample(&self, u: [f32; 2]) -> Option<(Vec3, Vec3, f32)> {
        if self.uniform {
            let d = crate::sampling::sample_uniform_sphere(u);
            return Some((d, self.radiance(d), 1.0 / (4.0 * PI)));
        }
        let (j, rest_v) = pick(&self.rows, u[0]);
        let row = &self.columns[j * self.width..(j + 1) * self.width];
        let (i, rest_u) = pick(row, u[1]);
        let uu = (i as f32 + rest_u) / self.width as f32;
        let vv = (j as f32 + rest_v) / self.height as f32;
        let (d, _) = self.direction(uu, vv);
        // Radiance and density from the direction itself, as a ray that escapes along it gets
        // them: on a cell's edge rounding may put it in the neighbour, and both must agree.
        let pdf = self.pdf(d);
        (pdf > 0.0 && d.is_finite()).then(|| (d, self.radiance(d), pdf))
    }
}

impl std::fmt::Debug for EnvMap {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        write!(f, "EnvMap({} x {})", self.width, self.height)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A dim sky with a small bright sun, 64 x 32.
    fn sunny(rotate: f32) -> EnvMap {
        let (w, h) = (64, 32);
        let texels: Vec<[f32; 3]> = (0..w * h)
            .map(|k| {
                let (i, j) = (k % w, k / w);
                if (20..22).contains(&i) && (9..11).contains(&j) {
                    [400.0, 380.0, 300.0]
                } else {
                    [0.2, 0.3, 0.5 + j as f32 / 64.0]
                }
            })
            .collect();
        EnvMap::new(w, h, &texels, 1.0, rotate).unwrap()
    }

    fn hash(k: u64) -> f32 {
        let mut z = k.wrapping_mul(0x9e37_79b9_7f4a_7c15);
        z = (z ^ (z >> 31)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        ((z >> 40) as f32) / (1u64 << 24) as f32
    }

    #[test]
    fn the_image_centre_faces_z_and_its_first_quarter_x() {
        let (w, h) = (4, 2);
        // Columns 0..3 carry their index in red.
        let texels: Vec<[f32; 3]> = (0..w * h).map(|k| [(k % w) as f32, 0.0, 0.0]).collect();
        let map = EnvMap::new(w, h, &texels, 1.0, 0.0).unwrap();
        let horizon = |x: f32, z: f32| map.radiance(Vec3::new(x, -0.01, z).normalize()).x;
        assert_eq!(horizon(-0.01, -1.0), 3.0, "just left of -Z is the right edge");
        assert_eq!(horizon(0.01, -1.0), 0.0, "-Z: the left edge");
        assert_eq!(horizon(1.0, 0.01), 1.0, "+X: the first quarter");
        assert_eq!(horizon(-0.01, 1.0), 2.0, "+Z: the centre, between columns 1 and 2");
        assert_eq!(horizon(0.01, 1.0), 1.0);
        // Turned 90 degrees about +Y, what faced +Z faces +X.
        let turned = EnvMap::new(w, h, &texels, 1.0, 90.0).unwrap();
        assert_eq!(turned.radiance(Vec3::new(1.0, -0.01, 0.01).normalize()).x, 2.0);
        for k in 0..50 {
            let (u, v) = (hash(2 * k), 0.02 + 0.96 * hash(2 * k + 1));
            let (d, _) = turned.direction(u, v);
            let (u2, v2) = turned.uv(d);
            assert!((u - u2).abs() < 1e-4 && (v - v2).abs() < 1e-4, "({u}, {v}) -> {d} -> ({u2}, {v2})");
        }
    }

    /// Chi-square of sampled directions against the pdf over a grid of solid-angle bins (fixed
    /// seed), against the statistic's critical value at significance 1e-4 (Wilson-Hilferty).
    #[test]
    fn sampled_directions_follow_the_pdf() {
        let map = sunny(30.0);
        let (nu, nv) = (24, 12);
        let samples = 200_000;
        let mut observed = vec![0u64; nu * nv];
        let bin = |d: Vec3| {
            let u = (atan2(d.x, -d.z) / (2.0 * PI)).rem_euclid(1.0);
            let v = acos(d.y.clamp(-1.0, 1.0)) / PI;
            ((v * nv as f32) as usize).min(nv - 1) * nu + ((u * nu as f32) as usize).min(nu - 1)
        };
        for k in 0..samples {
            // Only a pole (probability 0; a number of exactly 0) gives none.
            let Some((d, li, pdf)) = map.sample([hash(2 * k), hash(2 * k + 1)]) else { continue };
            assert_eq!(pdf, map.pdf(d));
            assert_eq!(li, map.radiance(d));
            observed[bin(d)] += 1;
        }
        // Expected counts by integrating the pdf over each bin (midpoint rule, 16 x 16 a bin).
        let sub = 16;
        let mut expected = vec![0f64; nu * nv];
        for (b, e) in expected.iter_mut().enumerate() {
            let (bu, bv) = (b % nu, b / nu);
            for s in 0..sub * sub {
                let u = (bu as f32 + ((s % sub) as f32 + 0.5) / sub as f32) / nu as f32;
                let v = (bv as f32 + ((s / sub) as f32 + 0.5) / sub as f32) / nv as f32;
                let theta = PI * v;
                let d = Vec3::new(sin(2.0 * PI * u) * sin(theta), cos(theta), -cos(2.0 * PI * u) * sin(theta));
                let area = (2.0 * PI / nu as f32) * (PI / nv as f32) * sin(theta) / (sub * sub) as f32;
                *e += (map.pdf(d) * area) as f64 * samples as f64;
            }
        }
        let total: f64 = expected.iter().sum();
        assert!((total / samples as f64 - 1.0).abs() < 0.01, "the pdf integrates to {}", total / samples as f64);
        let (mut chi2, mut dof) = (0.0, 0);
        for (o, e) in observed.iter().zip(&expected) {
            if *e >= 5.0 {
                chi2 += (*o as f64 - e).powi(2) / e;
                dof += 1;
            }
        }
        assert!(dof > 150, "{dof} bins");
        let k = (dof - 1) as f64;
        let critical = k * (1.0 - 2.0 / (9.0 * k) + 3.719 * (2.0 / (9.0 * k)).sqrt()).powi(3);
        assert!(chi2 < critical, "chi-square {chi2} over {dof} bins, critical {critical}");
    }

    #[test]
    fn the_pdf_integrates_to_one_and_bad_maps_are_refused() {
        let map = sunny(0.0);
        let n = 400;
        let mut integral = 0.0f64;
        for j in 0..n {
            for i in 0..2 * n {
                let (u, v) = ((i as f32 + 0.5) / (2 * n) as f32, (j as f32 + 0.5) / n as f32);
                let (d, sin_t) = map.direction(u, v);
                integral += (map.pdf(d) * sin_t) as f64 * (2.0 * PI as f64 / (2 * n) as f64) * (PI as f64 / n as f64);
            }
        }
        assert!((integral - 1.0).abs() < 2e-3, "{integral}");
        assert!(EnvMap::new(2, 1, &[[1.0, 0.0, f32::NAN], [0.0; 3]], 1.0, 0.0).unwrap_err().contains("(0, 0)"));
        assert!(EnvMap::new(2, 1, &[[0.0; 3], [-1.0, 0.0, 0.0]], 1.0, 0.0).unwrap_err().contains("(1, 0)"));
        assert!(EnvMap::new(0, 1, &[], 1.0, 0.0).is_err());
        assert!(EnvMap::new(1, 1, &[[1.0; 3]], -1.0, 0.0).is_err());
        // Sampled uniformly (for comparison), the density is 1 / 4 pi everywhere.
        let uniform = sunny(0.0).sampled_uniformly();
        let (d, li, pdf) = uniform.sample([0.3, 0.7]).unwrap();
        assert_eq!((pdf, uniform.pdf(Vec3::Y), li), (1.0 / (4.0 * PI), 1.0 / (4.0 * PI), uniform.radiance(d)));
        // A black map samples uniformly over its cells.
        let black = EnvMap::new(4, 2, &[[0.0; 3]; 8], 1.0, 0.0).unwrap();
        assert!(black.sample([0.3, 0.6]).is_some());
    }
}
