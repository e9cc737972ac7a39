//! What light transport carries along a path: three linear RGB channels (`Vec3`), or the
//! values at four hero wavelengths (`Vec4`). The BSDFs, lights and estimators are written once
//! over [`Channels`]; a [`ColorModel`] turns a scene's colours into channels for one path and
//! the path's result back into linear sRGB.

use crate::math::luminance;
use crate::spectral::Spectrum;
use glam::{Vec3, Vec4};
use std::fmt::Debug;
use std::ops::{Add, AddAssign, Div, DivAssign, Mul, MulAssign, Sub};

/// Per-channel radiometric values: radiance, throughput, reflectance.
pub trait Channels:
    Copy
    + 'static
    + Debug
    + PartialEq
    + Send
    + Sync
    + Add<Output = Self>
    + AddAssign
    + Sub<Output = Self>
    + Mul<Output = Self>
    + MulAssign
    + Mul<f32, Output = Self>
    + Div<f32, Output = Self>
    + DivAssign<f32>
{
    const ZERO: Self;
    const ONE: Self;
    fn splat(v: f32) -> Self;
    fn max_element(self) -> f32;
    fn min(self, other: Self) -> Self;
    fn max(self, other: Self) -> Self;
    /// One number for sampling decisions (lobe choice): luminance for RGB, the mean over
    /// wavelengths for spectral channels.
    fn weight(self) -> f32;
    /// Applies `f` channel by channel to `self` and `other`.
    fn zip_map(self, other: Self, f: impl Fn(f32, f32) -> f32) -> Self;
}

/// `Channels` for a glam vector type, with its `weight` and its lanes for `zip_map`.
macro_rules! channels_for {
    ($t:ident, $weight:expr, $($lane:ident),+) => {
        impl Channels for $t {
            const ZERO: Self = $t::ZERO;
            const ONE: Self = $t::ONE;
            fn splat(v: f32) -> Self {
                $t::splat(v)
            }
            fn max_element(self) -> f32 {
                $t::max_element(self)
            }
            fn min(self, other: Self) -> Self {
                $t::min(self, other)
            }
            fn max(self, other: Self) -> Self {
                $t::max(self, other)
            }
            fn weight(self) -> f32 {
                $weight(self)
            }
            fn zip_map(self, o: Self, f: impl Fn(f32, f32) -> f32) -> Self {
                $t::new($(f(self.$lane, o.$lane)),+)
            }
        }
    };
}

channels_for!(Vec3, luminance, x, y, z);
channels_for!(Vec4, |v: Vec4| 0.25 * v.element_sum(), x, y, z, w);

/// How one path sees the scene's colours.
pub trait ColorModel {
    type C: Channels;
    /// A reflectance given as linear sRGB in [0, 1] (base colours, textures).
    fn albedo(&self, rgb: Vec3) -> Self::C;
    /// An emitted radiance given as linear sRGB (emissive colours, lights, the environment):
    /// white is D65 when spectral.
    fn illuminant(&self, rgb: Vec3) -> Self::C;
    /// A measured spectrum times `scale`; `rgb` is what a model without wavelengths uses.
    fn measured(&self, spectrum: &Spectrum, scale: f32, rgb: Vec3) -> Self::C;
    /// An optical constant (`n` or `k`) given per RGB channel: its values at
    /// [`crate::spectral::RGB_WAVELENGTHS`], linear in between and constant beyond.
    fn optical_constant(&self, rgb: Vec3) -> Self::C;
    /// The path's channels as linear sRGB.
    fn to_rgb(&self, c: Self::C) -> Vec3;
}

/// Plain RGB transport: every colour is used as given.
#[derive(Clone, Copy, Debug, Default)]
pub struct Rgb;

impl ColorModel for Rgb {
    type C = Vec3;
    fn albedo(&self, rgb: Vec3) -> Vec3 {
        rgb
    }
    fn illuminant(&self, rgb: Vec3) -> Vec3 {
        rgb
    }
    fn measured(&self, _: &Spectrum, _: f32, rgb: Vec3) -> Vec3 {
        rgb
    }
    fn optical_constant(&self, rgb: Vec3) -> Vec3 {
        rgb
    }
    fn to_rgb(&self, c: Vec3) -> Vec3 {
        c
    }
}
