//! Error metrics between an image and a reference: RMSE and relative MSE.

use crate::ExrImage;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Comparison {
    /// Root mean squared error over pixels and channels.
    pub rmse: f64,
    /// Mean of `(a - b)^2 / (b^2 + 0.01)` over pixels and channels.
    pub rel_mse: f64,
    pub pixels_compared: usize,
    pub pixels_excluded: usize,
    /// Each image's mean R, G and B over the pixels compared.
    pub mean_image: [f64; 3],
    pub mean_reference: [f64; 3],
}

/// Compares `image` with `reference`; with `exclude_emitters`, pixels where either image's
/// camera rays saw an emitter are left out. `None` when the sizes differ.
pub fn compare(image: &ExrImage, reference: &ExrImage, exclude_emitters: bool) -> Option<Comparison> {
    compare_where(image, reference, |i| !(exclude_emitters && saw_emitter(image, reference, i)))
}

/// True when either image's camera rays saw an emitter directly at pixel `i` (its `emitter`
/// channel): the pixels `--exclude-emitters` leaves out.
pub fn saw_emitter(image: &ExrImage, reference: &ExrImage, i: usize) -> bool {
    image.emitter[i] > 0.0 || reference.emitter[i] > 0.0
}

/// Compares `image` with `reference` over the pixels `keep` keeps (by index). `None` when the
/// sizes differ.
pub fn compare_where(image: &ExrImage, reference: &ExrImage, keep: impl Fn(usize) -> bool) -> Option<Comparison> {
    if image.width != reference.width || image.height != reference.height {
        return None;
    }
    let (mut se, mut rel, mut n, mut excluded) = (0.0f64, 0.0f64, 0usize, 0usize);
    let (mut mean_image, mut mean_reference) = ([0.0f64; 3], [0.0f64; 3]);
    for i in 0..image.rgb.len() {
        if !keep(i) {
            excluded += 1;
            continue;
        }
        for k in 0..3 {
            let (a, b) = (image.rgb[i][k] as f64, reference.rgb[i][k] as f64);
            se += (a - b) * (a - b);
            rel += (a - b) * (a - b) / (b * b + 0.01);
            mean_image[k] += a;
            mean_reference[k] += b;
        }
        n += 1;
    }
    let count = (3 * n).max(1) as f64;
    let per_pixel = |m: [f64; 3]| m.map(|v| v / n.max(1) as f64);
    Some(Comparison {
        rmse: (se / count).sqrt(),
        rel_mse: rel / count,
        pixels_compared: n,
        pixels_excluded: excluded,
        mean_image: per_pixel(mean_image),
        mean_reference: per_pixel(mean_reference),
    })
}
