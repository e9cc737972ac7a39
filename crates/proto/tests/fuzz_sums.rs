//! Bounded fuzzing of the TSUM decoder, which reads what workers send and what the store holds:
//! random bytes, valid encodings mutated, and arbitrary plausible sums. The decoder must never
//! panic (this is a debug build: every overflow would), must refuse what it cannot read, and
//! what it accepts must be plausible and survive a round trip unchanged. The seed is fixed, so
//! CI runs the same cases every time; a failure proptest shrinks and prints becomes a test.

use proptest::prelude::*;
use tessera_proto::sums::{MAX_PIXEL_SAMPLES, decode_tile_sums, encode_tile_sums};
use tessera_render::glam::Vec3;
use tessera_render::{PixelSums, Tile, TileSums};

fn config() -> ProptestConfig {
    ProptestConfig {
        cases: 20_000,
        failure_persistence: None,
        rng_seed: proptest::test_runner::RngSeed::Fixed(0x7e55_e4a0),
        ..ProptestConfig::default()
    }
}

/// What an accepted result must satisfy, and the round trip.
fn check_accepted(bytes: &[u8]) {
    let Ok(sums) = decode_tile_sums(bytes) else { return };
    for p in &sums.pixels {
        assert!(p.n.checked_add(p.dropped).is_some_and(|s| s <= MAX_PIXEL_SAMPLES));
        assert!(p.emitter_hits <= p.n && p.hits <= p.n);
    }
    assert_eq!(decode_tile_sums(&encode_tile_sums(&sums)).unwrap(), sums);
}

fn a_real_result(width: u32, height: u32, seed: u32) -> Vec<u8> {
    let mut sums = TileSums::new(Tile { x0: 32, y0: 0, width, height });
    for (i, p) in sums.pixels.iter_mut().enumerate() {
        for k in 0..(i as u32 + seed) % 5 {
            let v = (i as f32 + k as f32) * 0.37 - 1.0;
            p.add_sample(Vec3::new(v, v * v, 1e3 * v), k % 2 == 0);
        }
    }
    encode_tile_sums(&sums)
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..600)) {
        check_accepted(&bytes);
        let mut with_header = b"TSUM\x03\0\0\0".to_vec();
        with_header.extend_from_slice(&bytes);
        check_accepted(&with_header);
    }

    #[test]
    fn mutated_results_never_panic(
        width in 1u32..6,
        height in 1u32..6,
        seed in 0u32..5,
        flips in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..6),
        cut in any::<prop::sample::Index>(),
        truncate in any::<bool>(),
    ) {
        let mut bytes = a_real_result(width, height, seed);
        for (at, value) in flips {
            let i = at.index(bytes.len());
            bytes[i] = value;
        }
        if truncate {
            bytes.truncate(cut.index(bytes.len()));
        }
        check_accepted(&bytes);
    }

    #[test]
    fn plausible_sums_round_trip(
        pixels in proptest::collection::vec((0u64..1 << 20, 0u64..100, any::<u64>(), any::<[i64; 3]>(), any::<[u64; 3]>()), 1..9),
    ) {
        let mut sums = TileSums::new(Tile { x0: 0, y0: 0, width: pixels.len() as u32, height: 1 });
        for (p, (n, dropped, hits, sum, sq)) in sums.pixels.iter_mut().zip(pixels) {
            // Sums within the reach of n samples of at most 2^30 each.
            let sum = sum.map(|v| (v as i128).clamp(-((n as i128) << 62), (n as i128) << 62));
            let sum_sq = sq.map(|v| (v as u128).min((n as u128) << 92));
            let below = |v: u64| if n == 0 { 0 } else { v % (n + 1) };
            *p = PixelSums { n, dropped, emitter_hits: below(hits), hits: below(hits.rotate_left(17)), sum, sum_sq };
        }
        prop_assert_eq!(decode_tile_sums(&encode_tile_sums(&sums)).unwrap(), sums);
    }
}
