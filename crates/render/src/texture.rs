//! Images and textures: 8- or 16-bit RGBA texels, glTF sampler wrap modes, bilinear filtering,
//! sRGB decoding of colour textures and KHR_texture_transform.

use glam::{Vec2, Vec4};

/// Decoded pixels, row-major from the top-left, RGBA.
#[derive(Clone, Debug)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub texels: Texels,
}

/// Texels at the depth of their file: 16-bit PNGs (normal and height maps, smooth gradients)
/// keep their 16 bits, since 8 would band where a mirror magnifies the slope of a normal map.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Texels {
    Eight(Vec<[u8; 4]>),
    Sixteen(Vec<[u16; 4]>),
}

impl Texels {
    pub fn len(&self) -> usize {
        match self {
            Texels::Eight(t) => t.len(),
            Texels::Sixteen(t) => t.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Texel `i` as linear floats; `srgb` decodes the colour channels (alpha is linear).
    fn decode(&self, i: usize, srgb: bool) -> Vec4 {
        match self {
            Texels::Eight(t) => decode(t[i], srgb),
            Texels::Sixteen(t) => decode16(t[i], srgb),
        }
    }
}

/// glTF sampler wrap modes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Wrap {
    Repeat,
    ClampToEdge,
    MirroredRepeat,
}

/// An image with a sampler (glTF `texture`).
#[derive(Clone, Copy, Debug)]
pub struct Texture {
    pub image: u32,
    pub wrap_s: Wrap,
    pub wrap_t: Wrap,
}

/// A material's reference to a texture: which texture, which UV set, and an optional
/// KHR_texture_transform (`uv' = M * (uv, 1)`, a 2x3 matrix in column order).
#[derive(Clone, Copy, Debug)]
pub struct TextureRef {
    pub texture: u32,
    pub texcoord: u32,
    pub transform: Option<[f32; 6]>,
}

impl TextureRef {
    pub fn apply_transform(&self, uv: Vec2) -> Vec2 {
        match self.transform {
            None => uv,
            Some(m) => Vec2::new(m[0] * uv.x + m[2] * uv.y + m[4], m[1] * uv.x + m[3] * uv.y + m[5]),
        }
    }
}

/// KHR_texture_transform as a 2x3 matrix: translation * rotation * scale, with the rotation
/// matrix of the extension's GLSL (columns `(cos, sin)` and `(-sin, cos)`).
pub fn texture_transform(offset: [f32; 2], rotation: f32, scale: [f32; 2]) -> [f32; 6] {
    let (s, c) = libm::sincosf(rotation);
    [c * scale[0], s * scale[0], -s * scale[1], c * scale[1], offset[0], offset[1]]
}

fn wrap(i: i64, n: u32, mode: Wrap) -> u32 {
    let n = n as i64;
    if (0..n).contains(&i) {
        // Every mode leaves a texel inside the image where it is (and most lookups' are):
        // no 64-bit division.
        return i as u32;
    }
    let j = match mode {
        Wrap::Repeat => i.rem_euclid(n),
        Wrap::ClampToEdge => i.clamp(0, n - 1),
        Wrap::MirroredRepeat => {
            let k = i.rem_euclid(2 * n);
            if k < n { k } else { 2 * n - 1 - k }
        }
    };
    j as u32
}

/// The sRGB transfer curve's inverse (IEC 61966-2-1), tabulated for 8-bit values.
fn srgb_to_linear_table() -> &'static [f32; 256] {
    static TABLE: std::sync::OnceLock<[f32; 256]> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        std::array::from_fn(|i| {
            let c = i as f32 / 255.0;
            if c <= 0.04045 { c / 12.92 } else { libm::powf((c + 0.055) / 1.055, 2.4) }
        })
    })
}

/// The sRGB transfer curve's inverse, tabulated for 16-bit values (256 KiB, made on first use).
fn srgb16_to_linear_table() -> &'static [f32] {
    static TABLE: std::sync::OnceLock<Vec<f32>> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        (0..=u16::MAX)
            .map(|i| {
                let c = i as f32 / 65535.0;
                if c <= 0.04045 { c / 12.92 } else { libm::powf((c + 0.055) / 1.055, 2.4) }
            })
            .collect()
    })
}

/// A 16-bit RGBA texel as linear floats; `srgb` decodes the colour channels (alpha is linear).
fn decode16(t: [u16; 4], srgb: bool) -> Vec4 {
    let channel = |v: u16| {
        if srgb { srgb16_to_linear_table()[v as usize] } else { v as f32 / 65535.0 }
    };
    Vec4::new(channel(t[0]), channel(t[1]), channel(t[2]), t[3] as f32 / 65535.0)
}

/// The four `texel`s at `corners` (top left, top right, bottom left, bottom right) weighted by
/// the lookup's place `fx`, `fy` between them.
#[inline(always)]
fn bilinear(texel: impl Fn(usize) -> Vec4, corners: [usize; 4], fx: f32, fy: f32) -> Vec4 {
    let top = texel(corners[0]).lerp(texel(corners[1]), fx);
    let bottom = texel(corners[2]).lerp(texel(corners[3]), fx);
    top.lerp(bottom, fy)
}

/// `v / 255` for each 8-bit value `v`, tabulated: a lookup where each channel took a division
/// (the same correctly rounded quotients, worked out when compiling).
static UNORM8: [f32; 256] = {
    let mut table = [0.0; 256];
    let mut v = 0;
    while v < 256 {
        table[v] = v as f32 / 255.0;
        v += 1;
    }
    table
};

/// The tables an 8-bit texel's colour channels and its alpha are decoded by.
fn tables8(srgb: bool) -> (&'static [f32; 256], &'static [f32; 256]) {
    (if srgb { srgb_to_linear_table() } else { &UNORM8 }, &UNORM8)
}

/// An 8-bit RGBA texel as linear floats by [`tables8`]'s tables.
#[inline(always)]
fn decode8(t: [u8; 4], (colour, alpha): (&[f32; 256], &[f32; 256])) -> Vec4 {
    Vec4::new(colour[t[0] as usize], colour[t[1] as usize], colour[t[2] as usize], alpha[t[3] as usize])
}

/// An 8-bit RGBA texel as linear floats; `srgb` decodes the colour channels (alpha is linear).
fn decode(t: [u8; 4], srgb: bool) -> Vec4 {
    decode8(t, tables8(srgb))
}

impl Image {
    /// Bilinearly filtered lookup; `srgb` decodes the colour channels to linear.
    pub fn sample(&self, uv: Vec2, wrap_s: Wrap, wrap_t: Wrap, srgb: bool) -> Vec4 {
        if self.width == 0 || self.height == 0 || !uv.is_finite() {
            return Vec4::ONE;
        }
        let x = uv.x * self.width as f32 - 0.5;
        let y = uv.y * self.height as f32 - 0.5;
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (x0, y0) = (x0 as i64, y0 as i64);
        let xs = [wrap(x0, self.width, wrap_s), wrap(x0 + 1, self.width, wrap_s)];
        let ys = [wrap(y0, self.height, wrap_t), wrap(y0 + 1, self.height, wrap_t)];
        let at = |x: u32, y: u32| (y * self.width + x) as usize;
        let corners = [at(xs[0], ys[0]), at(xs[1], ys[0]), at(xs[0], ys[1]), at(xs[1], ys[1])];
        // The texels' depth and tables chosen once for the four texels.
        match &self.texels {
            Texels::Eight(t) => {
                let tables = tables8(srgb);
                bilinear(|i| decode8(t[i], tables), corners, fx, fy)
            }
            Texels::Sixteen(t) => bilinear(|i| decode16(t[i], srgb), corners, fx, fy),
        }
    }

    /// Mean of each channel over the image (linear, after optional sRGB decoding).
    pub fn mean_value(&self, srgb: bool) -> Vec4 {
        if self.texels.is_empty() {
            return Vec4::ONE;
        }
        let sum = (0..self.texels.len()).fold(Vec4::ZERO, |acc, i| acc + self.texels.decode(i, srgb));
        sum / self.texels.len() as f32
    }

    /// Largest value of each channel over the image (linear, after optional sRGB decoding).
    pub fn max_value(&self, srgb: bool) -> Vec4 {
        fn channel_max<T: Copy + Ord + Default>(texels: &[[T; 4]]) -> [T; 4] {
            texels.iter().fold([T::default(); 4], |m, t| std::array::from_fn(|c| m[c].max(t[c])))
        }
        match &self.texels {
            Texels::Eight(t) => decode(channel_max(t), srgb),
            Texels::Sixteen(t) => decode16(channel_max(t), srgb),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrap_modes_follow_gltf() {
        assert_eq!(wrap(-1, 4, Wrap::Repeat), 3);
        assert_eq!(wrap(5, 4, Wrap::ClampToEdge), 3);
        assert_eq!(wrap(4, 4, Wrap::MirroredRepeat), 3);
        assert_eq!(wrap(-1, 4, Wrap::MirroredRepeat), 0);
    }

    #[test]
    fn eight_bit_texels_decode_to_their_quotients() {
        for v in 0..=255u8 {
            let linear = decode([v, v, v, v], false);
            assert_eq!(linear.to_array().map(f32::to_bits), [(v as f32 / 255.0).to_bits(); 4], "{v}");
            let srgb = decode([v, v, v, v], true);
            assert_eq!(srgb.w.to_bits(), (v as f32 / 255.0).to_bits(), "{v}: alpha stays linear");
            assert_eq!(srgb.x, srgb_to_linear_table()[v as usize], "{v}");
        }
    }

    #[test]
    fn srgb_decoding_matches_the_standard() {
        let t = srgb_to_linear_table();
        assert_eq!(t[0], 0.0);
        assert!((t[255] - 1.0).abs() < 1e-6);
        assert!((t[128] - 0.21586).abs() < 1e-4);
    }

    #[test]
    fn sixteen_bit_texels_keep_their_depth() {
        // 0x8000 and 0x80ff are the same 8-bit value (128); 16 bits tell them apart.
        let image = |v: u16| Image { width: 1, height: 1, texels: Texels::Sixteen(vec![[v, v, v, 0xffff]]) };
        let at = |v: u16, srgb: bool| image(v).sample(Vec2::splat(0.5), Wrap::Repeat, Wrap::Repeat, srgb);
        assert_eq!(at(0x8000, false).x, 32768.0 / 65535.0);
        assert!(at(0x80ff, false).x > at(0x8000, false).x);
        assert_eq!(at(0xffff, false), Vec4::ONE);
        // sRGB: the same curve as the 8-bit table where the values coincide (v * 257).
        for v in [0u8, 1, 10, 128, 254, 255] {
            let wide = at(v as u16 * 257, true).x;
            assert!((wide - srgb_to_linear_table()[v as usize]).abs() < 1e-6, "{v}: {wide}");
        }
        assert!(at(0x80ff, true).x > at(0x8000, true).x);
    }

    #[test]
    fn texture_transform_offsets_rotates_and_scales() {
        let r = TextureRef { texture: 0, texcoord: 0, transform: Some(texture_transform([0.5, 0.0], 0.0, [2.0, 2.0])) };
        assert_eq!(r.apply_transform(Vec2::new(1.0, 1.0)), Vec2::new(2.5, 2.0));
        let rot = texture_transform([0.0, 0.0], std::f32::consts::FRAC_PI_2, [1.0, 1.0]);
        let r = TextureRef { texture: 0, texcoord: 0, transform: Some(rot) };
        let v = r.apply_transform(Vec2::new(1.0, 0.0));
        assert!((v - Vec2::new(0.0, 1.0)).length() < 1e-6, "{v}");
    }
}
