//! The exact binary encoding of [`TileSums`]:
//!
//! ```text
//! "TSUM"  u32 format (4)  u32 x0  u32 y0  u32 width  u32 height     (little-endian)
//! per pixel, row-major, each an unsigned LEB128 varint:
//!     n  dropped  emitter_hits  hits  zigzag(sum[0..3])  sum_sq[0..3]
//!     format 5 only: zigzag(albedo[0..3])  zigzag(normal[0..3])       (the feature layers)
//! ```
//!
//! A result carries the feature layers (format 5) only when its render asked for them; without
//! them it is written in format 4, so asking for none costs nothing on the wire.
//!
//! `zigzag(v) = (v << 1) ^ (v >> 127)` maps the signed sums to unsigned ones, small magnitudes
//! to small numbers (protobuf's `sint`). Formats 3 (without `hits`, before transparent renders)
//! and 2 (unsigned sums too, before spectral renders could give negative sums) are still read,
//! their every sample counted as a hit, so results stored by an older coordinator stay usable.
//!
//! Integers travel as integers, so a merge on the coordinator gives the same bits as a merge in
//! the renderer. Varints make a typical pixel about 40 bytes instead of 120 (the 128-bit sums are
//! mostly leading zeros), which is what the coordinator's disk and network carry. Decoding checks
//! every length and refuses anything malformed.

use crate::WireError;
use tessera_render::{FeatureSums, PixelSums, Tile, TileSums};

const MAGIC: &[u8; 4] = b"TSUM";
const FORMAT: u32 = 4;
/// Format 4 with the feature layers' sums after each pixel's.
const FORMAT_FEATURES: u32 = 5;
/// The format before hits were counted.
const FORMAT_NO_HITS: u32 = 3;
/// The format before signed sums: `sum` unsigned, and no hits.
const FORMAT_UNSIGNED: u32 = 2;
/// The bytes of a result's header, before its pixels.
pub const HEADER_BYTES: usize = 4 + 4 * 5;
/// Longest encoding of one pixel: 4 u64 and 6 u128 varints.
pub const MAX_PIXEL_BYTES: usize = 4 * 10 + 6 * 19;
/// Longest encoding of one pixel with its feature layers: six more i64 varints.
pub const MAX_PIXEL_BYTES_WITH_FEATURES: usize = MAX_PIXEL_BYTES + 6 * 10;
/// Largest tile accepted on the wire (1024 x 1024 pixels).
pub const MAX_TILE_PIXELS: u64 = 1 << 20;
/// Most samples (merged and dropped) one pixel of a result may carry.
pub const MAX_PIXEL_SAMPLES: u64 = 1 << 32;
/// Largest quantum one sample adds to `sum` (`MAX_SAMPLE * 2^32`) and to `sum_sq`
/// (`MAX_SAMPLE^2 * 2^32`): the sums of `n` samples lie within `n` times these.
const MAX_SUM_QUANTUM: u128 = 1 << 62;
const MAX_SUM_SQ_QUANTUM: u128 = 1 << 92;
const _: () = assert!(tessera_render::MAX_SAMPLE as f64 * tessera_render::FIXED_POINT_SCALE == (1u64 << 62) as f64);

/// What two results are compared by (`--verify`): the BLAKE3 hash of their encoding. Sums are
/// integers and their encoding is canonical, so equal digests are equal sums; a result is
/// decoded and encoded again before its digest is taken, so a worker cannot make equal sums
/// look different by how it wrote them.
pub fn digest(sums: &TileSums) -> [u8; 32] {
    *blake3::hash(&encode_tile_sums(sums)).as_bytes()
}

pub fn encode_tile_sums(sums: &TileSums) -> Vec<u8> {
    let t = sums.tile;
    let mut out = Vec::with_capacity(HEADER_BYTES + sums.pixels.len() * 40);
    out.extend_from_slice(MAGIC);
    let with_features = !sums.features.is_empty();
    let format = if with_features { FORMAT_FEATURES } else { FORMAT };
    for v in [format, t.x0, t.y0, t.width, t.height] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    for (i, p) in sums.pixels.iter().enumerate() {
        for v in [p.n, p.dropped, p.emitter_hits, p.hits] {
            put_varint(&mut out, v as u128);
        }
        for &v in &p.sum {
            put_varint(&mut out, zigzag(v));
        }
        for &v in &p.sum_sq {
            put_varint(&mut out, v);
        }
        if with_features {
            let f = sums.features.get(i).copied().unwrap_or_default();
            for v in f.albedo.into_iter().chain(f.normal) {
                put_varint(&mut out, zigzag(v as i128));
            }
        }
    }
    out
}

fn zigzag(v: i128) -> u128 {
    ((v << 1) ^ (v >> 127)) as u128
}

fn unzigzag(v: u128) -> i128 {
    ((v >> 1) as i128) ^ -((v & 1) as i128)
}

fn put_varint(out: &mut Vec<u8>, mut v: u128) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

/// Reads one varint of at most `max_bits` bits (64 or 128) at `*at`.
///
/// The coordinator decodes every result it is sent (about 40 varints a pixel), so this is its
/// hottest loop: it finds the varint's end first, then gathers seven bits a byte into a `u64`,
/// and into a `u128` only past the ninth byte. It refuses what `reference_varint` in the tests
/// refuses, with the same message.
#[inline]
fn get_varint(bytes: &[u8], at: &mut usize, max_bits: u32) -> Result<u128, WireError> {
    let start = *at;
    let rest = bytes.get(start..).unwrap_or_default();
    // Bytes a varint of `max_bits` may span; one more only ever overflows.
    let most = max_bits.div_ceil(7) as usize;
    // The byte at `most - 1` may carry only the bits that are left.
    let overflows = |i: usize| {
        let shift = 7 * i as u32;
        i > 0 && max_bits - shift < 7 && (rest[i] & 0x7F) >> (max_bits - shift) != 0
    };
    let overflow = |i: usize| WireError::Sums(format!("a value at byte {} overflows {max_bits} bits", start + i));
    let Some(len) = rest.iter().take(most).position(|b| b & 0x80 == 0).map(|i| i + 1) else {
        return Err(match rest.len() {
            n if n >= most && overflows(most - 1) => overflow(most - 1),
            n if n > most => overflow(most),
            _ => WireError::Sums(format!("truncated at byte {}", bytes.len())),
        });
    };
    if overflows(len - 1) {
        return Err(overflow(len - 1));
    }
    *at = start + len;
    let mut low = 0u64;
    for (i, &b) in rest[..len.min(9)].iter().enumerate() {
        low |= ((b & 0x7F) as u64) << (7 * i);
    }
    let mut v = low as u128;
    for (i, &b) in rest[..len].iter().enumerate().skip(9) {
        v |= ((b & 0x7F) as u128) << (7 * i);
    }
    Ok(v)
}

/// Sums no run of samples can produce are refused, so that a forged result can neither wrap a
/// counter nor overflow a film that merges it: `n + dropped` at most [`MAX_PIXEL_SAMPLES`],
/// `emitter_hits <= n`, `hits <= n`, `|sum| <= n 2^62`, `sum_sq <= n 2^92`.
fn check_plausible(p: &PixelSums) -> Result<(), String> {
    let samples = p.n.checked_add(p.dropped).filter(|&s| s <= MAX_PIXEL_SAMPLES);
    if samples.is_none() {
        return Err(format!("{} samples and {} dropped is more than a pixel may carry", p.n, p.dropped));
    }
    if p.emitter_hits > p.n {
        return Err(format!("{} emitter hits among {} samples", p.emitter_hits, p.n));
    }
    if p.hits > p.n {
        return Err(format!("{} camera rays hit the scene among {} samples", p.hits, p.n));
    }
    let n = p.n as u128;
    for k in 0..3 {
        if p.sum[k].unsigned_abs() > n * MAX_SUM_QUANTUM || p.sum_sq[k] > n * MAX_SUM_SQ_QUANTUM {
            return Err(format!("channel {k}'s sums are out of reach of {} samples", p.n));
        }
    }
    Ok(())
}

pub fn decode_tile_sums(bytes: &[u8]) -> Result<TileSums, WireError> {
    let bad = |m: String| WireError::Sums(m);
    if bytes.len() < HEADER_BYTES {
        return Err(bad(format!("{} bytes is shorter than the {HEADER_BYTES}-byte header", bytes.len())));
    }
    if &bytes[..4] != MAGIC {
        return Err(bad("missing the TSUM marker".into()));
    }
    let word = |i: usize| u32::from_le_bytes([bytes[4 + 4 * i], bytes[5 + 4 * i], bytes[6 + 4 * i], bytes[7 + 4 * i]]);
    let format = word(0);
    if !(FORMAT_UNSIGNED..=FORMAT_FEATURES).contains(&format) {
        return Err(bad(format!("format {format} is not a supported format ({FORMAT_UNSIGNED} to {FORMAT_FEATURES})")));
    }
    let with_hits = format >= FORMAT;
    let with_features = format == FORMAT_FEATURES;
    let most_bytes = if with_features { MAX_PIXEL_BYTES_WITH_FEATURES } else { MAX_PIXEL_BYTES };
    let tile = Tile { x0: word(1), y0: word(2), width: word(3), height: word(4) };
    let pixels = tile.width as u64 * tile.height as u64;
    if pixels == 0 || pixels > MAX_TILE_PIXELS {
        return Err(bad(format!(
            "a {}x{} tile is empty or over the {MAX_TILE_PIXELS}-pixel limit",
            tile.width, tile.height
        )));
    }
    if ((bytes.len() - HEADER_BYTES) as u64) < pixels * 9
        || ((bytes.len() - HEADER_BYTES) as u64) > pixels * most_bytes as u64
    {
        return Err(bad(format!("{} bytes cannot hold a {}x{} tile", bytes.len(), tile.width, tile.height)));
    }
    let mut at = HEADER_BYTES;
    let mut out = Vec::with_capacity(pixels as usize);
    let mut features = Vec::with_capacity(if with_features { pixels as usize } else { 0 });
    for _ in 0..pixels {
        let mut small = [0u64; 4];
        for v in &mut small[..if with_hits { 4 } else { 3 }] {
            *v = get_varint(bytes, &mut at, 64)? as u64;
        }
        if !with_hits {
            small[3] = small[0]; // before hits were counted, every camera ray counts as one
        }
        let mut sum = [0i128; 3];
        for v in &mut sum {
            let raw = get_varint(bytes, &mut at, 128)?;
            *v = if format >= FORMAT_NO_HITS {
                unzigzag(raw)
            } else {
                i128::try_from(raw).map_err(|_| bad(format!("a format-2 sum at byte {at} overflows")))?
            };
        }
        let mut sum_sq = [0u128; 3];
        for v in &mut sum_sq {
            *v = get_varint(bytes, &mut at, 128)?;
        }
        let pixel = PixelSums { n: small[0], dropped: small[1], emitter_hits: small[2], hits: small[3], sum, sum_sq };
        check_plausible(&pixel).map_err(|m| bad(format!("pixel {} of the tile: {m}", out.len())))?;
        if with_features {
            let mut values = [0i64; 6];
            for v in &mut values {
                let raw = unzigzag(get_varint(bytes, &mut at, 64)?);
                *v = i64::try_from(raw).map_err(|_| bad(format!("a feature sum at byte {at} overflows")))?;
            }
            let f =
                FeatureSums { albedo: [values[0], values[1], values[2]], normal: [values[3], values[4], values[5]] };
            check_features(&f, &pixel).map_err(|m| bad(format!("pixel {} of the tile: {m}", out.len())))?;
            features.push(f);
        }
        out.push(pixel);
    }
    if at != bytes.len() {
        return Err(bad(format!("{} bytes left over after the tile's pixels", bytes.len() - at)));
    }
    Ok(TileSums { tile, pixels: out, features })
}

/// Feature sums no run of the pixel's samples can produce are refused: each sample adds an
/// albedo in [0, 2^24] and a normal in [-2^24, 2^24] per component, over `n + dropped` samples
/// (a sample whose colour was dropped still has its features).
fn check_features(f: &FeatureSums, p: &PixelSums) -> Result<(), String> {
    let most = (p.n + p.dropped) as i128 * tessera_render::FEATURE_SCALE as i128;
    let albedo_ok = f.albedo.iter().all(|&v| (0..=most).contains(&(v as i128)));
    let normal_ok = f.normal.iter().all(|&v| (v as i128).abs() <= most);
    if albedo_ok && normal_ok {
        Ok(())
    } else {
        Err(format!("feature sums out of reach of {} samples", p.n + p.dropped))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tessera_render::glam::Vec3;

    fn sample_sums() -> TileSums {
        let mut s = TileSums::new(Tile { x0: 32, y0: 64, width: 5, height: 3 });
        for (i, p) in s.pixels.iter_mut().enumerate() {
            p.add_sample(Vec3::new(i as f32, 0.5, 1e6), i % 2 == 0);
            p.add_sample(Vec3::new(f32::NAN, 0.0, 0.0), false);
            p.add(Vec3::ZERO, false, i % 3 == 0); // a camera ray that missed, in most pixels
            // The largest sums that `n` samples can reach survive too.
            p.sum[2] = -((p.n as i128) << 62);
            p.sum[1] = (p.n as i128) << 62;
            p.sum_sq[2] = (p.n as u128) << 92;
        }
        s
    }

    #[test]
    fn forged_counts_and_sums_are_refused() {
        let forge = |f: &dyn Fn(&mut PixelSums)| {
            let mut s = sample_sums();
            f(&mut s.pixels[3]);
            decode_tile_sums(&encode_tile_sums(&s)).unwrap_err().to_string()
        };
        // n = 2^64 - 1 and 17 dropped wrapped to 16 samples and merged garbage.
        let e = forge(&|p| (p.n, p.dropped) = (u64::MAX, 17));
        assert!(e.contains("pixel 3") && e.contains("more than a pixel may carry"), "{e}");
        assert!(forge(&|p| p.n = MAX_PIXEL_SAMPLES + 1).contains("more than a pixel may carry"));
        assert!(forge(&|p| p.emitter_hits = p.n + 1).contains("emitter hits"));
        assert!(forge(&|p| p.hits = p.n + 1).contains("hit the scene"));
        assert!(forge(&|p| p.sum[0] = i128::MIN).contains("out of reach"));
        assert!(forge(&|p| p.sum[1] = ((p.n as i128) << 62) + 1).contains("out of reach"));
        assert!(forge(&|p| p.sum_sq[2] = u128::MAX).contains("out of reach"));
        assert!(forge(&|p| (p.n, p.hits, p.sum[0]) = (0, 0, 1)).contains("out of reach"), "no samples, no sum");
    }

    #[test]
    fn round_trip_is_exact() {
        let s = sample_sums();
        assert_eq!(decode_tile_sums(&encode_tile_sums(&s)).unwrap(), s);
    }

    /// Feature layers travel in format 5, exactly; without them a result stays format 4, byte for
    /// byte what it was; sums no samples could give are refused.
    #[test]
    fn feature_layers_round_trip_and_are_checked() {
        let plain = sample_sums();
        let plain_bytes = encode_tile_sums(&plain);
        assert_eq!(u32::from_le_bytes(plain_bytes[4..8].try_into().unwrap()), 4);
        let mut s = plain.clone();
        s.features = vec![FeatureSums::default(); s.pixels.len()];
        for (i, f) in s.features.iter_mut().enumerate() {
            f.add(Vec3::new(0.25, 1.0, 0.0), Vec3::new(-1.0, 0.5, i as f32 * 0.1));
            f.add(Vec3::splat(0.8), Vec3::new(0.0, -0.25, 1.0));
        }
        let bytes = encode_tile_sums(&s);
        assert_eq!(u32::from_le_bytes(bytes[4..8].try_into().unwrap()), 5);
        assert_eq!(decode_tile_sums(&bytes).unwrap(), s);
        assert!(bytes.len() > plain_bytes.len());
        let forge = |f: &dyn Fn(&mut FeatureSums)| {
            let mut s = s.clone();
            f(&mut s.features[2]);
            decode_tile_sums(&encode_tile_sums(&s)).unwrap_err().to_string()
        };
        // Pixel 2 holds 3 samples (one dropped): at most 3 * 2^24 per component.
        assert!(forge(&|f| f.albedo[0] = -1).contains("feature sums out of reach"));
        assert!(forge(&|f| f.normal[1] = 3 * (1 << 24) + 1).contains("feature sums out of reach"));
        assert!(forge(&|f| f.albedo[2] = i64::MAX).contains("pixel 2"));
    }

    #[test]
    fn results_in_the_older_formats_still_decode_as_hits() {
        let mut s = TileSums::new(Tile { x0: 0, y0: 0, width: 2, height: 1 });
        s.pixels[0].add_sample(Vec3::new(0.25, 3.0, 1e6), true);
        s.pixels[1].add_sample(Vec3::new(1.0, 0.0, 0.5), false);
        s.pixels[1].add_sample(Vec3::new(0.5, 0.0, 0.5), false);
        // Format 2 wrote every sum as a plain unsigned varint, format 3 zigzagged the signed
        // ones; neither counted hits (every sample above is one).
        for format in [FORMAT_UNSIGNED, FORMAT_NO_HITS] {
            let mut old = Vec::new();
            old.extend_from_slice(MAGIC);
            for v in [format, 0, 0, 2, 1] {
                old.extend_from_slice(&v.to_le_bytes());
            }
            for p in &s.pixels {
                let small = [p.n, p.dropped, p.emitter_hits].map(|v| v as u128);
                let sums = p.sum.map(|v| if format == FORMAT_UNSIGNED { v as u128 } else { zigzag(v) });
                for v in small.into_iter().chain(sums).chain(p.sum_sq) {
                    put_varint(&mut old, v);
                }
            }
            assert_eq!(decode_tile_sums(&old).unwrap(), s, "format {format}");
            assert_ne!(old, encode_tile_sums(&s), "format {FORMAT} is what is written");
        }
    }

    #[test]
    fn zigzag_keeps_small_magnitudes_small() {
        for v in [0i128, 1, -1, 63, -64, i128::MAX, i128::MIN] {
            assert_eq!(unzigzag(zigzag(v)), v);
        }
        assert_eq!(zigzag(-1), 1);
        assert_eq!(zigzag(1), 2);
    }

    /// The plain reading of a varint, a byte at a time: what `get_varint` must agree with.
    fn reference_varint(bytes: &[u8], at: &mut usize, max_bits: u32) -> Result<u128, WireError> {
        let mut v: u128 = 0;
        let mut shift = 0u32;
        loop {
            let Some(&b) = bytes.get(*at) else {
                return Err(WireError::Sums(format!("truncated at byte {}", *at)));
            };
            *at += 1;
            if shift >= max_bits || (shift > 0 && max_bits - shift < 7 && (b & 0x7F) >> (max_bits - shift) != 0) {
                return Err(WireError::Sums(format!("a value at byte {} overflows {max_bits} bits", *at - 1)));
            }
            v |= ((b & 0x7F) as u128) << shift;
            if b & 0x80 == 0 {
                return Ok(v);
            }
            shift += 7;
        }
    }

    /// The fast varint reader reads and refuses exactly what the plain one does: every value
    /// around each length's edges, every overlong or truncated form, and pseudo-random bytes.
    #[test]
    fn varints_read_as_the_plain_reading_does() {
        let mut cases: Vec<Vec<u8>> = Vec::new();
        for bits in 0..=128u32 {
            for v in [1u128.checked_shl(bits).unwrap_or(0).wrapping_sub(1), 1u128.checked_shl(bits).unwrap_or(0)] {
                let mut out = Vec::new();
                put_varint(&mut out, v);
                cases.push(out.clone());
                cases.push(out[..out.len() - 1].to_vec()); // truncated
                let mut longer = out.clone();
                *longer.last_mut().unwrap() |= 0x80;
                longer.extend_from_slice(&[0x80, 0x01]); // overlong
                cases.push(longer);
            }
        }
        for len in 1..24 {
            cases.push([vec![0xFF; len - 1], vec![0x7F]].concat());
            cases.push(vec![0x80; len]);
        }
        let mut x = 0x9E37_79B9_7F4A_7C15u64;
        for _ in 0..20_000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            let len = (x % 24) as usize;
            cases.push((0..len).map(|i| (x >> (i % 8 * 8)) as u8 | if i + 1 < len { 0x80 } else { 0 }).collect());
        }
        for bytes in &cases {
            for max_bits in [64, 128] {
                let (mut a, mut b) = (0, 0);
                let fast = get_varint(bytes, &mut a, max_bits).map_err(|e| e.to_string());
                let plain = reference_varint(bytes, &mut b, max_bits).map_err(|e| e.to_string());
                assert_eq!(fast, plain, "{bytes:02x?} as {max_bits} bits");
                if fast.is_ok() {
                    assert_eq!(a, b, "{bytes:02x?}: where the next value starts");
                }
            }
        }
    }

    #[test]
    fn malformed_bytes_are_refused() {
        let bytes = encode_tile_sums(&sample_sums());
        for cut in [0, 3, 10, HEADER_BYTES, bytes.len() - 1] {
            assert!(decode_tile_sums(&bytes[..cut]).is_err(), "cut at {cut}");
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(decode_tile_sums(&longer).is_err());
        let mut wrong = bytes.clone();
        wrong[0] = b'X';
        assert!(decode_tile_sums(&wrong).unwrap_err().to_string().contains("TSUM"));
        let mut huge = bytes.clone();
        huge[16..20].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(decode_tile_sums(&huge).unwrap_err().to_string().contains("limit"));
        let noise: Vec<u8> = (0..5000u32).map(|i| (i.wrapping_mul(2_654_435_761) >> 11) as u8).collect();
        assert!(decode_tile_sums(&noise).is_err());
    }
}
