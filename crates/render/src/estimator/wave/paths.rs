//! The lanes' state: rows of eight numbers ([`Rows`]), the paths in the lanes ([`Paths`]), and
//! the tile's samples in the pixel loop's order ([`Queue`]).

use super::{Row, W};
use crate::sampler::{PixelSampler, PixelSeeds};
use crate::settings::RenderSettings;
use crate::sums::{Tile, TileSums};
use glam::{Vec2, Vec3};
use std::ops::Range;

/// Three rows: a vector per lane.
#[derive(Clone, Copy, Default)]
pub(super) struct Rows(pub(super) [Row; 3]);

impl Rows {
    #[inline(always)]
    pub(super) fn get(&self, i: usize) -> Vec3 {
        Vec3::new(self.0[0][i], self.0[1][i], self.0[2][i])
    }

    #[inline(always)]
    pub(super) fn set(&mut self, i: usize, v: Vec3) {
        (self.0[0][i], self.0[1][i], self.0[2][i]) = (v.x, v.y, v.z);
    }
}

/// The paths in the lanes.
pub(super) struct Paths {
    pub(super) live: [bool; W],
    pub(super) pixel: [usize; W],
    pub(super) sampler: [PixelSampler; W],
    /// Whether the camera ray met the scene (the pixel's coverage), set by the first step.
    pub(super) covered: [bool; W],
    pub(super) bounce: [u32; W],
    pub(super) o: Rows,
    pub(super) d: Rows,
    pub(super) beta: Rows,
    pub(super) l: Rows,
    pub(super) saw_emitter: [bool; W],
    pub(super) prev_pdf: Row,
    pub(super) prev_delta: [bool; W],
    pub(super) prev_p: Rows,
    pub(super) prev_n: Rows,
}

impl Paths {
    pub(super) fn new() -> Self {
        let idle = PixelSampler::new(crate::sampler::SamplerKind::Independent, 0, (0, 0), 0);
        Self {
            live: [false; W],
            pixel: [0; W],
            sampler: [idle; W],
            covered: [false; W],
            bounce: [0; W],
            o: Rows::default(),
            d: Rows::default(),
            beta: Rows::default(),
            l: Rows::default(),
            saw_emitter: [false; W],
            prev_pdf: [0.0; W],
            prev_delta: [true; W],
            prev_p: Rows::default(),
            prev_n: Rows::default(),
        }
    }

    /// Lane `i` takes the sample `sampler` of pixel `pixel` (its index in the tile), whose camera
    /// ray is `o + t d`.
    #[inline(always)]
    pub(super) fn start(&mut self, i: usize, pixel: usize, sampler: PixelSampler, o: Vec3, d: Vec3) {
        self.live[i] = true;
        self.pixel[i] = pixel;
        self.sampler[i] = sampler;
        self.covered[i] = false;
        self.bounce[i] = 0;
        self.o.set(i, o);
        self.d.set(i, d);
        self.beta.set(i, Vec3::ONE);
        self.l.set(i, Vec3::ZERO);
        self.saw_emitter[i] = false;
        self.prev_pdf[i] = 0.0;
        self.prev_delta[i] = true;
        self.prev_p.set(i, o);
        self.prev_n.set(i, Vec3::Z);
    }

    /// Lane `i`'s path ends: its sample goes to its pixel.
    #[inline(always)]
    pub(super) fn finish(&mut self, i: usize, sums: &mut TileSums) {
        sums.pixels[self.pixel[i]].add(self.l.get(i), self.saw_emitter[i], self.covered[i]);
        self.live[i] = false;
    }
}

/// The tile's samples in the pixel loop's order: pixel by pixel, each pixel's indices in turn.
pub(super) struct Queue {
    tile: Tile,
    samples: Range<u32>,
    kind: crate::sampler::SamplerKind,
    seed: u64,
    /// The pixel (index in the tile) being handed out, its seeds and its next sample index.
    pixel: usize,
    seeds: Option<PixelSeeds>,
    index: u32,
}

impl Queue {
    pub(super) fn new(settings: &RenderSettings, tile: Tile, samples: Range<u32>) -> Self {
        let index = samples.start;
        Self { tile, samples, kind: settings.sampler, seed: settings.seed, pixel: 0, seeds: None, index }
    }

    /// The next sample: its pixel's index in the tile, its sampler and the point of the film
    /// its camera numbers choose. Box filter: every sample stays inside its own pixel.
    #[inline(always)]
    pub(super) fn next(&mut self) -> Option<(usize, PixelSampler, Vec2)> {
        let pixels = (self.tile.width * self.tile.height) as usize;
        loop {
            if self.pixel >= pixels || self.samples.is_empty() {
                return None;
            }
            let (px, py) = ((self.pixel as u32) % self.tile.width, (self.pixel as u32) / self.tile.width);
            let (x, y) = (self.tile.x0 + px, self.tile.y0 + py);
            if self.index < self.samples.end {
                let seeds = self.seeds.get_or_insert_with(|| PixelSeeds::new(self.kind, self.seed, (x, y)));
                let (sampler, c) = seeds.camera(self.index);
                self.index += 1;
                return Some((self.pixel, sampler, Vec2::new(x as f32 + c[0], y as f32 + c[1])));
            }
            (self.pixel, self.seeds, self.index) = (self.pixel + 1, None, self.samples.start);
        }
    }
}
