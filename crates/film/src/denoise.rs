//! Denoising a resolved image: the [`Denoiser`] interface the binary fills in when it is built
//! with Open Image Denoise (`tessera-denoise`), and the `denoised` layer it writes. The film's
//! sums and the raw channels are never touched: denoising only adds a layer.

use crate::{ExrImage, FilmError};

/// Denoises a colour image with the help of its albedo and normal layers. Implementations run
/// one image at a time and may take seconds on a large frame: call them outside any lock.
pub trait Denoiser: Send + Sync {
    /// Who denoises, with version and mode, for the image's header (`denoiser=...`).
    fn name(&self) -> String;

    /// The denoised colour of a `width` x `height` image; every slice is row-major from the
    /// top-left, one entry per pixel.
    fn denoise(
        &self,
        width: u32,
        height: u32,
        color: &[[f32; 3]],
        albedo: &[[f32; 3]],
        normal: &[[f32; 3]],
    ) -> Result<Vec<[f32; 3]>, String>;
}

impl ExrImage {
    /// Adds the `denoised` layer (which the PNG then shows) and names the denoiser in the
    /// header. The image must carry its feature layers.
    pub fn denoise_with(&mut self, denoiser: &dyn Denoiser) -> Result<(), FilmError> {
        let fail = |message: String| FilmError::Denoise(message);
        let features = self
            .features
            .as_ref()
            .ok_or_else(|| fail("the image has no albedo and normal layers to denoise with".into()))?;
        let denoised =
            denoiser.denoise(self.width, self.height, &self.rgb, &features.albedo, &features.normal).map_err(fail)?;
        if denoised.len() != self.rgb.len() {
            return Err(fail(format!("the denoiser returned {} pixels for {}", denoised.len(), self.rgb.len())));
        }
        if denoised.iter().flatten().any(|c| !c.is_finite()) {
            return Err(fail("the denoiser returned values that are not finite".into()));
        }
        self.denoised = Some(denoised);
        self.metadata += &format!("denoiser={}\n", denoiser.name());
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{FeatureLayers, read_exr, write_exr, write_png};

    /// A stand-in that averages each pixel with its right neighbour, or fails when told to.
    struct Smear {
        fail: bool,
    }

    impl Denoiser for Smear {
        fn name(&self) -> String {
            "smear 1.0".into()
        }
        fn denoise(
            &self,
            w: u32,
            _: u32,
            c: &[[f32; 3]],
            _: &[[f32; 3]],
            _: &[[f32; 3]],
        ) -> Result<Vec<[f32; 3]>, String> {
            if self.fail {
                return Err("out of memory".into());
            }
            let next = |i: usize| c[if (i + 1).is_multiple_of(w as usize) { i } else { i + 1 }];
            Ok((0..c.len()).map(|i| [0, 1, 2].map(|k| (c[i][k] + next(i)[k]) / 2.0)).collect())
        }
    }

    fn image() -> ExrImage {
        let rgb = vec![[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.0, 0.5, 1.0], [1.0, 0.5, 0.0]];
        let mut image = ExrImage::from_rgb(2, 2, rgb, "scene=test\n".into());
        image.features = Some(FeatureLayers { albedo: vec![[0.5; 3]; 4], normal: vec![[0.0, 0.0, 1.0]; 4] });
        image
    }

    /// The denoised layer is added beside the untouched colour, named in the header, written to
    /// the EXR as `denoised.R/G/B` and back, and shown by the PNG.
    #[test]
    fn denoising_adds_a_layer_and_leaves_the_raw_colour_alone() {
        let raw = image();
        let mut denoised = raw.clone();
        denoised.denoise_with(&Smear { fail: false }).unwrap();
        assert_eq!(denoised.rgb, raw.rgb, "the raw colour changed");
        assert_eq!(denoised.denoised.as_deref(), Some(&[[0.5; 3], [1.0; 3], [0.5, 0.5, 0.5], [1.0, 0.5, 0.0]][..]));
        assert!(denoised.metadata.ends_with("denoiser=smear 1.0\n"), "{}", denoised.metadata);
        let dir = tempfile::tempdir().unwrap();
        write_exr(&denoised, &dir.path().join("d.exr")).unwrap();
        assert_eq!(read_exr(&dir.path().join("d.exr")).unwrap(), denoised);
        write_exr(&raw, &dir.path().join("r.exr")).unwrap();
        assert_eq!(read_exr(&dir.path().join("r.exr")).unwrap().denoised, None);
        let png = |image: &ExrImage, name: &str| {
            write_png(image, &dir.path().join(name)).unwrap();
            image::open(dir.path().join(name)).unwrap().to_rgb8().get_pixel(0, 0).0
        };
        assert_eq!(png(&raw, "r.png"), [0, 0, 0]);
        assert_eq!(png(&denoised, "d.png"), [188, 188, 188], "the PNG is not the denoised colour");
    }

    #[test]
    fn denoising_needs_the_layers_and_reports_the_denoisers_failure() {
        let mut plain = image();
        plain.features = None;
        let err = plain.denoise_with(&Smear { fail: false }).unwrap_err().to_string();
        assert!(err.contains("no albedo and normal layers"), "{err}");
        let mut image = image();
        let err = image.denoise_with(&Smear { fail: true }).unwrap_err().to_string();
        assert_eq!(err, "denoising failed: out of memory");
        assert_eq!((image.denoised, image.metadata), (None, "scene=test\n".to_string()));
    }
}
