//! Denoising finished images. With the `oidn` feature (what `tessera-cli/denoise` turns on),
//! [`denoiser`] gives Open Image Denoise 2.x on the CPU; without it, an error that says how to
//! build a `tessera` that denoises. The film's sums and raw channels are never touched: the
//! denoised colour is a layer of its own ([`tessera_film::ExrImage::denoise_with`]).

use std::sync::Arc;

pub use tessera_film::Denoiser;

#[cfg(feature = "oidn")]
mod open_image_denoise;

/// What a binary built without denoising says when asked to denoise.
pub const NOT_BUILT: &str = "this tessera was built without denoising. Build one that denoises \
with `cargo build --release --features tessera-cli/denoise`, with Open Image Denoise 2.x where \
OIDN_DIR points: an OIDN release folder, or the `pyoidn` wheel's (`pip install pyoidn`, then \
OIDN_DIR=$(python3 -c 'import pyoidn, os; print(os.path.dirname(pyoidn.__file__))')/oidn)";

/// Whether this build can denoise at all (it was built with Open Image Denoise).
pub const BUILT_IN: bool = cfg!(feature = "oidn");

/// The denoiser of this build: Open Image Denoise on the CPU, started here (it loads its CPU
/// module, so this fails where the library's files are incomplete), or [`NOT_BUILT`].
pub fn denoiser() -> Result<Arc<dyn Denoiser>, String> {
    #[cfg(feature = "oidn")]
    {
        Ok(Arc::new(open_image_denoise::Oidn::start()?))
    }
    #[cfg(not(feature = "oidn"))]
    {
        Err(NOT_BUILT.to_string())
    }
}
