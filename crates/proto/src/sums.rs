//! The exact binary encoding of [`TileSums`] (little-endian):
//!
//! ```text
//! "TSUM"  u32 format (1)  u32 x0  u32 y0  u32 width  u32 height
//! per pixel, row-major: u64 n  u64 dropped  u64 emitter_hits  u128 sum[3]  u128 sum_sq[3]
//! ```
//!
//! Integers travel as integers, so a merge on the coordinator gives the same bits as a merge in
//! the renderer. Decoding checks every length and refuses anything malformed.

use crate::WireError;
use tessera_render::{PixelSums, Tile, TileSums};

const MAGIC: &[u8; 4] = b"TSUM";
const FORMAT: u32 = 1;
const HEADER_BYTES: usize = 4 + 4 * 5;
pub const PIXEL_BYTES: usize = 3 * 8 + 6 * 16;
/// Largest tile accepted on the wire (1024 x 1024 pixels, 120 MiB encoded).
pub const MAX_TILE_PIXELS: u64 = 1 << 20;

pub fn encode_tile_sums(sums: &TileSums) -> Vec<u8> {
    let t = sums.tile;
    let mut out = Vec::with_capacity(HEADER_BYTES + sums.pixels.len() * PIXEL_BYTES);
    out.extend_from_slice(MAGIC);
    for v in [FORMAT, t.x0, t.y0, t.width, t.height] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    for p in &sums.pixels {
        for v in [p.n, p.dropped, p.emitter_hits] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for v in p.sum.iter().chain(&p.sum_sq) {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

pub fn decode_tile_sums(bytes: &[u8]) -> Result<TileSums, WireError> {
    let bad = |m: String| WireError::Sums(m);
    if bytes.len() < HEADER_BYTES {
        return Err(bad(format!(
            "{} bytes is shorter than the {HEADER_BYTES}-byte header",
            bytes.len()
        )));
    }
    if &bytes[..4] != MAGIC {
        return Err(bad("missing the TSUM marker".into()));
    }
    let word = |i: usize| {
        u32::from_le_bytes([
            bytes[4 + 4 * i],
            bytes[5 + 4 * i],
            bytes[6 + 4 * i],
            bytes[7 + 4 * i],
        ])
    };
    let format = word(0);
    if format != FORMAT {
        return Err(bad(format!(
            "format {format} is not the supported format {FORMAT}"
        )));
    }
    let tile = Tile {
        x0: word(1),
        y0: word(2),
        width: word(3),
        height: word(4),
    };
    let pixels = tile.width as u64 * tile.height as u64;
    if pixels == 0 || pixels > MAX_TILE_PIXELS {
        return Err(bad(format!(
            "a {}x{} tile is empty or over the {MAX_TILE_PIXELS}-pixel limit",
            tile.width, tile.height
        )));
    }
    let expected = HEADER_BYTES as u64 + pixels * PIXEL_BYTES as u64;
    if bytes.len() as u64 != expected {
        return Err(bad(format!(
            "{} bytes for a {}x{} tile, expected {expected}",
            bytes.len(),
            tile.width,
            tile.height
        )));
    }
    let body = &bytes[HEADER_BYTES..];
    let pixels = body
        .chunks_exact(PIXEL_BYTES)
        .map(|c| {
            let u64_at = |i: usize| u64::from_le_bytes(c[i..i + 8].try_into().expect("8 bytes"));
            let u128_at =
                |i: usize| u128::from_le_bytes(c[i..i + 16].try_into().expect("16 bytes"));
            PixelSums {
                n: u64_at(0),
                dropped: u64_at(8),
                emitter_hits: u64_at(16),
                sum: [u128_at(24), u128_at(40), u128_at(56)],
                sum_sq: [u128_at(72), u128_at(88), u128_at(104)],
            }
        })
        .collect();
    Ok(TileSums { tile, pixels })
}

#[cfg(test)]
mod tests {
    use super::*;
    use tessera_render::glam::Vec3;

    fn sample_sums() -> TileSums {
        let mut s = TileSums::new(Tile {
            x0: 32,
            y0: 64,
            width: 5,
            height: 3,
        });
        for (i, p) in s.pixels.iter_mut().enumerate() {
            p.add_sample(Vec3::new(i as f32, 0.5, 1e6), i % 2 == 0);
            p.add_sample(Vec3::new(f32::NAN, 0.0, 0.0), false);
        }
        s
    }

    #[test]
    fn round_trip_is_exact() {
        let s = sample_sums();
        assert_eq!(decode_tile_sums(&encode_tile_sums(&s)).unwrap(), s);
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
        assert!(
            decode_tile_sums(&wrong)
                .unwrap_err()
                .to_string()
                .contains("TSUM")
        );
        let mut huge = bytes.clone();
        huge[16..20].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(
            decode_tile_sums(&huge)
                .unwrap_err()
                .to_string()
                .contains("limit")
        );
        let noise: Vec<u8> = (0..5000u32)
            .map(|i| (i.wrapping_mul(2_654_435_761) >> 11) as u8)
            .collect();
        assert!(decode_tile_sums(&noise).is_err());
    }
}
