//! Planning, the one place that divides work: a render is tiles x passes; a pass is `pass_spp`
//! consecutive sample indices of one tile (the last pass of a tile may be shorter). Jobs are runs
//! of consecutive passes of a tile, sized from the worker's measured speed; adaptive sampling
//! gives tiles their passes in rounds; a sequence is frames, each at its own time with its own
//! seed. `tessera render`, the coordinator and the worker all plan with these functions, so that
//! they divide the same work alike (invariant 6).

use crate::Tile;
use std::fmt;
use std::ops::Range;

/// Default tile side and samples per pass, of `tessera render` and of farm submissions.
pub const TILE_SIZE: u32 = 32;
pub const PASS_SPP: u32 = 16;

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RenderPlan {
    pub tiles: Vec<Tile>,
    pub spp: u32,
    pub pass_spp: u32,
}

impl RenderPlan {
    pub fn new(width: u32, height: u32, tile_size: u32, spp: u32, pass_spp: u32) -> Self {
        Self { tiles: Tile::grid(width, height, tile_size.max(1)), spp, pass_spp: pass_spp.max(1) }
    }

    pub fn passes_per_tile(&self) -> u32 {
        self.spp.div_ceil(self.pass_spp)
    }

    pub fn total_passes(&self) -> u64 {
        self.tiles.len() as u64 * self.passes_per_tile() as u64
    }

    /// Sample indices of passes `first .. first + count` of any tile.
    pub fn samples(&self, first: u32, count: u32) -> Range<u32> {
        pass_samples(first, count, self.pass_spp, self.spp)
    }
}

/// Sample indices of passes `first .. first + count` of `pass_spp` samples each, of a tile of
/// `spp` samples (the last pass may be shorter; passes past the end are empty).
pub fn pass_samples(first: u32, count: u32, pass_spp: u32, spp: u32) -> Range<u32> {
    let at = |pass: u64| (pass * pass_spp as u64).min(spp as u64) as u32;
    at(first as u64)..at(first as u64 + count as u64)
}

/// Adaptive sampling, shared by the coordinator and `tessera render` so that both decide alike:
/// a tile first gets the passes that cover `min_spp` (at least one, at most `max`) ...
pub fn first_round(min_spp: u32, pass_spp: u32, max: u32) -> u32 {
    min_spp.div_ceil(pass_spp.max(1)).clamp(1, max.max(1))
}

/// ... and once all `passes` of its round are merged, a tile whose relative error is still above
/// the target doubles them, up to `max`; `None` when it is done. The error is
/// `tessera_film::relative_error` of the tile's merged pixels, a pure function of the samples,
/// so the rounds are the same however the passes were spread over workers and threads.
pub fn next_round(passes: u32, max: u32, error: f64, target: f64) -> Option<u32> {
    (error > target && passes < max).then(|| passes.saturating_mul(2).min(max))
}

/// The passes a tile of `plan` is predicted to end with, given its relative `error` with
/// `passes` merged: [`next_round`]'s rounds, with the error falling as 1/sqrt(samples) (a pixel
/// mean's variance falls as 1/n). For quotes and ETAs only: no sample depends on it.
pub fn predicted_passes(plan: &RenderPlan, passes: u32, error: f64, target: f64) -> u32 {
    let (max, n0) = (plan.passes_per_tile(), plan.samples(0, passes).len().max(1) as f64);
    let mut b = passes;
    loop {
        let n = plan.samples(0, b).len().max(1) as f64;
        match next_round(b, max, error * (n0 / n).sqrt(), target) {
            Some(next) => b = next,
            None => return b,
        }
    }
}

/// How far a pilot's error may be off, each way, for a quote's range: a tile's error estimated
/// from its first round (16 samples a pixel by default) moves by about this much between seeds
/// on the scenes tested, more where rare bright paths dominate.
pub const ERROR_SPREAD: f64 = 1.25;

/// Most tiles a quote's pilot renders (spread over the image): a few seconds on a laptop.
pub const PILOT_TILES: usize = 64;

/// The tiles a pilot of at most `most` of `count` tiles renders: spread evenly over the image.
pub fn pilot_tiles(count: usize, most: usize) -> Vec<usize> {
    let k = count.min(most.max(1));
    (0..k).map(|i| i * count / k).collect()
}

/// How many passes to put in one job for a worker rendering `samples_per_second`, so that the
/// job takes about `target_seconds`: big jobs for fast workers, at least one pass, at most `max`.
/// An unknown speed (0) gets one pass, which measures it.
pub fn job_passes(samples_per_second: f64, tile_pixels: u64, pass_spp: u32, target_seconds: f64, max: u32) -> u32 {
    let per_pass = (tile_pixels * pass_spp as u64).max(1) as f64;
    if !(samples_per_second.is_finite() && samples_per_second > 0.0) {
        return 1;
    }
    let passes = (samples_per_second * target_seconds / per_pass).floor();
    (passes as u32).clamp(1, max.max(1))
}

/// Most frames one sequence may hold.
pub const MAX_FRAMES: usize = 100_000;
/// Largest frame number: frame numbers are written with up to seven digits.
pub const MAX_FRAME: u32 = 9_999_999;

/// The frames of a sequence, in the order given: `1-48`, `1-48x2` (every second frame), `1,5,9`,
/// or a comma-separated mix, as render farms write them.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FrameList(pub Vec<u32>);

impl FrameList {
    pub fn parse(s: &str) -> Result<FrameList, String> {
        let number = |n: &str, what: &str| -> Result<u32, String> {
            let n = n.trim();
            let v: u64 = n.parse().map_err(|_| format!("'{n}' is not a frame number ({what} in '{s}')"))?;
            if v > MAX_FRAME as u64 {
                return Err(format!("frame {v} is past the last frame number, {MAX_FRAME}"));
            }
            Ok(v as u32)
        };
        if s.trim().is_empty() {
            return Err("the frame list is empty: give frames like 1-48, 1-48x2 or 1,5,9".into());
        }
        let mut frames = Vec::new();
        let mut seen = std::collections::HashSet::new();
        for item in s.split(',') {
            let item = item.trim();
            let (range, step) = match item.split_once('x') {
                Some((r, st)) => (r, number(st, "a step")?),
                None => (item, 1),
            };
            if step == 0 {
                return Err(format!("'{item}': the step must be at least 1"));
            }
            let (first, last) = match range.split_once('-') {
                Some((a, b)) => (number(a, "a range's start")?, number(b, "a range's end")?),
                None if item.contains('x') => return Err(format!("'{item}': a step needs a range, as in 1-48x2")),
                None => {
                    let f = number(range, "a frame")?;
                    (f, f)
                }
            };
            if last < first {
                return Err(format!("'{item}' runs backwards: write {last}-{first}"));
            }
            let count = ((last - first) / step) as usize + 1;
            if frames.len() + count > MAX_FRAMES {
                return Err(format!("'{s}' holds more than {MAX_FRAMES} frames"));
            }
            for f in (first..=last).step_by(step as usize) {
                if !seen.insert(f) {
                    return Err(format!("frame {f} is listed twice in '{s}'"));
                }
                frames.push(f);
            }
        }
        Ok(FrameList(frames))
    }
}

impl fmt::Display for FrameList {
    /// Runs of consecutive frames as ranges: "1-48,60".
    fn fmt(&self, f: &mut fmt::Formatter) -> fmt::Result {
        let mut parts = Vec::new();
        let mut i = 0;
        while i < self.0.len() {
            let mut j = i;
            while j + 1 < self.0.len() && self.0[j + 1] == self.0[j] + 1 {
                j += 1;
            }
            parts.push(if i == j { format!("{}", self.0[i]) } else { format!("{}-{}", self.0[i], self.0[j]) });
            i = j + 1;
        }
        write!(f, "{}", parts.join(","))
    }
}

/// The time of frame `frame` at `fps` frames a second, in seconds.
pub fn frame_time(frame: u32, fps: f64) -> f32 {
    (frame as f64 / fps) as f32
}

/// The render seed of frame `frame` of a sequence rendered with seed `seed`: each frame draws
/// its own samples, so that noise does not stand still on the screen while the picture moves,
/// and a frame's seed depends on nothing but the two numbers (SplitMix64's finaliser of both).
pub fn frame_seed(seed: u64, frame: u32) -> u64 {
    let mut z = seed ^ (frame as u64 + 1).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A tile at error 0.1 after one 16-spp pass needs four times the samples for 0.05: rounds
    /// 1 -> 2 (0.0707) -> 4 (0.05, done); one already below the target stays; the cap holds.
    #[test]
    fn predicted_passes_follow_the_rounds_with_the_error_falling_as_one_over_root_n() {
        let plan = RenderPlan::new(64, 64, 32, 1024, 16);
        assert_eq!(predicted_passes(&plan, 1, 0.1, 0.05), 4);
        assert_eq!(predicted_passes(&plan, 1, 0.1001, 0.05), 8);
        assert_eq!(predicted_passes(&plan, 2, 0.01, 0.05), 2);
        assert_eq!(predicted_passes(&plan, 1, 10.0, 0.05), 64, "at most the render's spp");
    }

    #[test]
    fn passes_cover_every_sample_once() {
        let plan = RenderPlan::new(100, 60, 32, 50, 16);
        assert_eq!(plan.passes_per_tile(), 4);
        assert_eq!(plan.tiles.len(), 4 * 2);
        let mut covered = Vec::new();
        for p in 0..plan.passes_per_tile() {
            covered.extend(plan.samples(p, 1));
        }
        assert_eq!(covered, (0..50).collect::<Vec<_>>());
        assert_eq!(plan.samples(1, 3), 16..50);
        assert_eq!(plan.samples(3, 9), 48..50);
        assert_eq!(plan.samples(9, 1), 50..50);
        assert_eq!(pass_samples(u32::MAX, u32::MAX, 1 << 16, 1 << 20), (1 << 20)..(1 << 20), "no arithmetic wraps");
    }

    #[test]
    fn rounds_double_until_the_target_or_the_cap() {
        assert_eq!(first_round(0, 16, 8), 1);
        assert_eq!(first_round(40, 16, 8), 3);
        assert_eq!(first_round(1 << 20, 16, 8), 8);
        assert_eq!(next_round(3, 8, 0.5, 0.1), Some(6));
        assert_eq!(next_round(6, 8, 0.5, 0.1), Some(8));
        assert_eq!(next_round(8, 8, 0.5, 0.1), None);
        assert_eq!(next_round(3, 8, 0.1, 0.1), None, "a tile at the target is done");
        assert_eq!(next_round(3, 8, f64::NAN, 0.1), None);
    }

    #[test]
    fn fast_workers_get_bigger_jobs() {
        let slow = job_passes(1e5, 1024, 16, 2.0, 64);
        let fast = job_passes(4e6, 1024, 16, 2.0, 64);
        assert_eq!(slow, 12);
        assert!(fast > slow && fast <= 64);
        assert_eq!(job_passes(0.0, 1024, 16, 2.0, 64), 1);
        assert_eq!(job_passes(f64::NAN, 1024, 16, 2.0, 64), 1);
        assert_eq!(job_passes(1.0, 1024, 16, 2.0, 64), 1);
    }

    #[test]
    fn frame_lists_read_as_farms_write_them() {
        let p = |s: &str| FrameList::parse(s).map(|f| f.0);
        assert_eq!(p("1-5").unwrap(), [1, 2, 3, 4, 5]);
        assert_eq!(p("1-9x3").unwrap(), [1, 4, 7]);
        assert_eq!(p("1,5,9").unwrap(), [1, 5, 9]);
        assert_eq!(p(" 0-2, 10 ").unwrap(), [0, 1, 2, 10]);
        assert_eq!(FrameList(vec![1, 2, 3, 7, 9, 10]).to_string(), "1-3,7,9-10");
        for (bad, says) in [
            ("", "empty"),
            ("5-1", "runs backwards"),
            ("1-100001", "more than 100000"),
            ("1-10x0", "at least 1"),
            ("a-3", "not a frame number"),
            ("1;2", "not a frame number"),
            ("-3", "not a frame number"),
            ("1,1", "listed twice"),
            ("5x2", "needs a range"),
            ("99999999", "past the last"),
        ] {
            let err = p(bad).unwrap_err();
            assert!(err.contains(says), "{bad}: {err}");
        }
    }

    #[test]
    fn frames_draw_their_own_seeds() {
        let seeds: std::collections::HashSet<u64> = (0..1000).map(|f| frame_seed(7, f)).collect();
        assert_eq!(seeds.len(), 1000);
        assert_ne!(frame_seed(7, 1), frame_seed(8, 1));
        assert_eq!(frame_time(36, 24.0), 1.5);
    }
}
