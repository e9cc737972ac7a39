//! Counts kept as renders change, so that no status, listing, stream or lease walks every render
//! or every frame of a sequence: each render's share (its kind, passes, samples, film) is
//! counted again whenever it changes ([`Core::recount`]) and the difference added to the farm's
//! sums and to its sequence's [`Tally`]. A sequence of 100,000 frames then costs a status, a
//! listing row or a stream's tick what a still does.

use super::{Core, Span, film_bytes};
use crate::model::{FrameDone, RenderState};
use std::collections::{BTreeMap, BTreeSet, HashMap};

/// What a render counts as in its sequence's row.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(super) enum Kind {
    /// Not there (forgotten, or being replaced by a retry).
    #[default]
    Gone,
    /// Running, nothing merged yet.
    Queued,
    /// Running with passes merged, or having its image written.
    Running,
    Done,
    Failed,
    Cancelled,
}

const KINDS: usize = 6;

impl Kind {
    fn index(self) -> usize {
        self as usize
    }
}

/// One render's share of the counts, as last counted.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(super) struct Share {
    /// Its sequence (0 for a still).
    pub sequence: i64,
    pub kind: Kind,
    pub passes_done: u64,
    pub passes_total: u64,
    pub samples_done: u64,
    /// Its error estimate once it is done (a running render's changes with every merge and is
    /// estimated when asked for).
    pub error: f64,
    /// Bytes of film it holds or will hold (see [`Core::film_bytes_held`]).
    pub film_bytes: u64,
}

/// A sequence's frames summed: by kind, passes, samples, errors of the finished ones, the failed
/// ones (for the first failure's message) and the finished ones in the order they finished.
#[derive(Clone, Debug)]
pub(super) struct Tally {
    pub scene_name: String,
    pub owner: String,
    pub frames: u32,
    by_kind: [u32; KINDS],
    pub passes_done: u64,
    pub passes_total: u64,
    pub samples_done: u64,
    /// Error estimates of the finished frames, summed (their mean is the sequence's).
    pub error_sum: f64,
    pub failed: BTreeSet<i64>,
    /// Frames in the order they finished: a watch tells each once, from where it got to.
    pub finished: Vec<i64>,
    /// Frames whose preview image was written (previews first), in that order.
    pub previewed: Vec<i64>,
    /// From its start to when its last frame ended (none running or queued).
    pub span: Span,
}

impl Tally {
    pub fn new(scene_name: &str, owner: &str, frames: u32) -> Self {
        Self {
            scene_name: scene_name.to_string(),
            owner: owner.to_string(),
            frames,
            by_kind: [0; KINDS],
            passes_done: 0,
            passes_total: 0,
            samples_done: 0,
            error_sum: 0.0,
            failed: BTreeSet::new(),
            finished: Vec::new(),
            previewed: Vec::new(),
            span: Span::default(),
        }
    }

    pub fn count(&self, kind: Kind) -> u32 {
        self.by_kind[kind.index()]
    }

    /// Frame `id`'s share changed from `old` to `new`.
    fn apply(&mut self, id: i64, old: &Share, new: &Share) {
        self.by_kind[old.kind.index()] -= 1;
        self.by_kind[new.kind.index()] += 1;
        self.passes_done = self.passes_done + new.passes_done - old.passes_done;
        self.passes_total = self.passes_total + new.passes_total - old.passes_total;
        self.samples_done = self.samples_done + new.samples_done - old.samples_done;
        if old.kind == Kind::Done {
            self.error_sum -= old.error;
        }
        if new.kind == Kind::Done {
            self.error_sum += new.error;
            if old.kind != Kind::Done {
                self.finished.push(id);
            }
        }
        self.span.running(self.count(Kind::Running) + self.count(Kind::Queued) > 0);
        match (old.kind == Kind::Failed, new.kind == Kind::Failed) {
            (false, true) => {
                self.failed.insert(id);
            }
            (true, false) => {
                self.failed.remove(&id);
            }
            _ => {}
        }
    }
}

/// The counts of the whole farm.
#[derive(Debug, Default)]
pub(super) struct Counts {
    shares: HashMap<i64, Share>,
    /// Bytes of film all renders hold or will hold.
    pub film_bytes: u64,
    /// Renders in state running (queued, rendering or being written), in id order.
    pub running: BTreeSet<i64>,
    pub tallies: BTreeMap<i64, Tally>,
}

impl Core {
    /// Render `id`'s share as it stands now (`Kind::Gone` if there is no such render).
    pub(super) fn share_now(&self, id: i64) -> Share {
        #[cfg(test)]
        self.reads.set(self.reads.get() + 1);
        if let Some(stored) = self.failed.get(&id) {
            return Share { sequence: stored.sequence, kind: Kind::Failed, ..Share::default() };
        }
        let Some(r) = self.renders.get(&id) else { return Share::default() };
        let passes_done = match r.state {
            RenderState::Done => r.passes_total,
            RenderState::Running if r.writing => r.passes_total,
            RenderState::Running => self.leases.progress(id as u64).map_or(0, |(merged, _)| merged),
            // Out of the lease table: what it merged before it stopped stays counted.
            RenderState::Cancelled | RenderState::Failed => r.film_passes.iter().map(|&n| n as u64).sum(),
        };
        let kind = match r.state {
            RenderState::Running if r.writing || passes_done > 0 => Kind::Running,
            RenderState::Running => Kind::Queued,
            RenderState::Done => Kind::Done,
            RenderState::Failed => Kind::Failed,
            RenderState::Cancelled => Kind::Cancelled,
        };
        // A running still's film is counted from its submit (it is allocated with its first
        // result); a frame's from when it starts; a film being written until it is written.
        let holds_film =
            !r.film.pixels.is_empty() || r.writing || (r.state == RenderState::Running && r.stored.sequence == 0);
        Share {
            sequence: r.stored.sequence,
            kind,
            passes_done,
            passes_total: r.passes_total,
            samples_done: r.samples_done,
            error: if kind == Kind::Done { r.final_error.estimate } else { 0.0 },
            film_bytes: if holds_film { film_bytes(&r.setup.settings) } else { 0 },
        }
    }

    /// Counts render `id` again after a change to it (its state, its passes, its film, or its
    /// being there at all), adding the difference to the farm's sums and its sequence's tally.
    pub(super) fn recount(&mut self, id: i64) {
        let (mut started, mut ended) = (None, None);
        if let Some(r) = self.renders.get_mut(&id) {
            let before = r.span.ended_at;
            r.span.running(r.state == RenderState::Running);
            started = r.span.started_at.map(|at| (r.stored.sequence, at));
            ended = (r.span.ended_at != before).then_some(r.span.ended_at.unwrap_or(0.0));
        }
        // Stored as the span has it, so that its figures read back the same after a restart.
        if let Some(at) = ended {
            self.write(crate::store::Write::Ended { render: id, at });
        }
        // A sequence ran from its earliest frame's start.
        if let Some((seq, at)) = started.filter(|&(seq, _)| seq != 0)
            && let Some(t) = self.counts.tallies.get_mut(&seq)
        {
            t.span.started_by(at);
        }
        let new = self.share_now(id);
        let counts = &mut self.counts;
        let old = match new.kind {
            Kind::Gone => counts.shares.remove(&id),
            _ => counts.shares.insert(id, new),
        }
        .unwrap_or_default();
        if old == new {
            return;
        }
        counts.film_bytes = counts.film_bytes + new.film_bytes - old.film_bytes;
        if matches!(new.kind, Kind::Queued | Kind::Running) {
            counts.running.insert(id);
        } else {
            counts.running.remove(&id);
        }
        let sequence = if new.kind == Kind::Gone { old.sequence } else { new.sequence };
        if let Some(tally) = counts.tallies.get_mut(&sequence) {
            tally.apply(id, &old, &new);
        }
    }

    /// Renders and sequences running, a sequence counted once: the running renders in id order,
    /// a sequence's frames (whose ids follow each other) skipped at once.
    pub(super) fn targets_running(&self) -> usize {
        let (mut n, mut from) = (0, i64::MIN);
        while let Some(&id) = self.counts.running.range(from..).next() {
            n += 1;
            from = match self.renders.get(&id).map(|r| r.stored.sequence) {
                Some(seq) if seq != 0 => seq + self.sequences.get(&seq).map_or(0, |f| f.len() as i64),
                _ => id,
            }
            .max(id + 1);
        }
        n
    }

    /// Frames of sequences queued or rendering.
    pub(super) fn frames_running(&self) -> usize {
        self.counts.tallies.values().map(|t| (t.count(Kind::Queued) + t.count(Kind::Running)) as usize).sum()
    }

    /// Counts a new sequence of `frames` frames (before its frames are counted).
    pub(super) fn count_sequence(&mut self, sequence: i64, scene_name: &str, owner: &str, frames: u32) {
        let mut tally = Tally::new(scene_name, owner, frames);
        tally.by_kind[Kind::Gone.index()] = frames;
        self.counts.tallies.insert(sequence, tally);
    }

    /// Frames of sequence `seq` finished after the first `from` to finish, in the order they
    /// finished, at most `limit` of them; and how many have finished in all.
    pub fn finished_frames(&self, seq: i64, from: usize, limit: usize) -> (Vec<FrameDone>, usize) {
        self.frames_in(seq, |t| &t.finished, from, limit)
    }

    /// The frames of sequence `seq` that `list` picks from its tally (finished, previewed),
    /// from the `from`-th on (at most `limit`), and how many it lists.
    pub(super) fn frames_in(
        &self,
        seq: i64,
        list: impl Fn(&Tally) -> &Vec<i64>,
        from: usize,
        limit: usize,
    ) -> (Vec<FrameDone>, usize) {
        let Some(ids) = self.counts.tallies.get(&seq).map(list) else { return (Vec::new(), 0) };
        let frames = ids
            .iter()
            .skip(from)
            .take(limit)
            .map(|&id| FrameDone { frame: self.frame_of(id).unwrap_or(0), render_id: id.to_string() })
            .collect();
        (frames, ids.len())
    }

    /// Checks every count against the renders counted from scratch (tests call it after every
    /// change the engine makes).
    #[cfg(test)]
    pub(crate) fn audit(&self) {
        let ids: BTreeSet<i64> = self.renders.keys().chain(self.failed.keys()).copied().collect();
        let shares: HashMap<i64, Share> = ids.iter().map(|&id| (id, self.share_now(id))).collect();
        assert_eq!(shares, self.counts.shares, "every render's share is counted as it stands");
        let film: u64 = shares.values().map(|s| s.film_bytes).sum();
        assert_eq!(film, self.counts.film_bytes, "film bytes");
        let running: BTreeSet<i64> =
            self.renders.iter().filter(|(_, r)| r.state == RenderState::Running).map(|(&id, _)| id).collect();
        assert_eq!(running, self.counts.running, "running renders");
        assert_eq!(
            self.sequences.keys().collect::<Vec<_>>(),
            self.counts.tallies.keys().collect::<Vec<_>>(),
            "one tally a sequence"
        );
        for (seq, frames) in &self.sequences {
            let tally = &self.counts.tallies[seq];
            let mut fresh = Tally::new(&tally.scene_name, &tally.owner, frames.len() as u32);
            fresh.by_kind[Kind::Gone.index()] = frames.len() as u32;
            for &id in frames {
                if let Some(share) = shares.get(&id) {
                    fresh.apply(id, &Share::default(), share);
                }
            }
            assert_eq!(fresh.by_kind, tally.by_kind, "sequence s{seq}: frames by kind");
            assert_eq!(
                (fresh.passes_done, fresh.passes_total, fresh.samples_done),
                (tally.passes_done, tally.passes_total, tally.samples_done),
                "sequence s{seq}: passes and samples"
            );
            assert!((fresh.error_sum - tally.error_sum).abs() <= 1e-9 * fresh.error_sum.max(1.0));
            assert_eq!(fresh.failed, tally.failed, "sequence s{seq}: failed frames");
            let finished: BTreeSet<i64> = tally.finished.iter().copied().collect();
            let done: BTreeSet<i64> = fresh.finished.iter().copied().collect();
            assert!(done.is_subset(&finished), "sequence s{seq}: every finished frame is listed");
            assert_eq!(finished.len(), tally.finished.len(), "sequence s{seq}: each finished frame listed once");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::{fixed, fresh_dir, on, submitted};
    use super::*;
    use crate::core::Target;
    use crate::model::{Frames, Pose, Submission};
    use tessera_render::RenderSettings;
    use tessera_render::plan::FrameList;

    /// A sequence of `frames` frames of 8 x 8 pixels, one tile, one 4-sample pass each.
    fn tiny_sequence(frames: u32) -> Submission {
        let mut req = Submission { spp: 4, tile_size: 8, ..fixed() };
        req.setup.settings = RenderSettings { seed: 3, ..RenderSettings::new(8, 8) };
        req.frames = Some(Frames { list: FrameList::parse(&format!("1-{frames}")).unwrap(), fps: 24.0 });
        req.setup.pose = Some(Pose::default());
        req
    }

    #[tokio::test]
    async fn a_long_sequence_costs_a_status_and_a_listing_what_a_still_does() {
        const FRAMES: u32 = 5000;
        let dir = fresh_dir("long-sequence");
        let (engine, before) = submitted(dir.path()).await;
        let seq = engine.submit(&crate::users::Identity::anyone(), tiny_sequence(FRAMES)).await.unwrap().id();
        let after = engine.submit(&crate::users::Identity::anyone(), fixed()).await.unwrap().id();
        // A status, a listing and the metrics read a few renders, not the sequence's frames
        // (counted from scratch they would read every one).
        let (s, rows, reads) = on(&engine, |c| {
            let start = c.reads.get();
            let s = c.status_of(Target::Sequence(seq)).unwrap();
            let (rows, more) = c.list_renders(0, 500, |_| true);
            assert!(!more);
            let metrics = c.farm_metrics();
            assert_eq!((metrics.pending_frames, metrics.renders_running), (FRAMES as usize, FRAMES as usize + 2));
            (s, rows, c.reads.get() - start)
        });
        assert!(reads <= 8, "{reads} renders read for a status, a listing and the metrics");
        assert_eq!((s.frames_total, s.frames_queued, s.passes_total), (FRAMES, FRAMES, FRAMES as u64));
        let ids: Vec<String> = rows.iter().map(|r| r.render_id.clone()).collect();
        assert_eq!(ids, [before.to_string(), format!("s{seq}"), after.to_string()]);
        // Pages of one row step over the frames; a page that begins inside the sequence
        // does not list it again.
        let page = |after_id: i64| {
            on(&engine, |c| {
                let (rows, more) = c.list_renders(after_id, 1, |_| true);
                (rows.iter().map(|r| r.render_id.clone()).collect::<Vec<_>>(), more)
            })
        };
        assert_eq!(page(0), (vec![before.to_string()], true));
        assert_eq!(page(before), (vec![format!("s{seq}")], true));
        assert_eq!(page(seq), (vec![after.to_string()], false));
        assert_eq!(page(seq + 10), (vec![after.to_string()], false));
        // Another user's sequence is stepped over as well.
        assert_eq!(on(&engine, |c| c.list_renders(0, 10, |owner| owner == "someone").0.len()), 0);
        // Cancelled, every frame counts as cancelled at once.
        engine.cancel(Target::Sequence(seq)).await.unwrap();
        let s = on(&engine, |c| c.status_of(Target::Sequence(seq)).unwrap());
        assert_eq!((s.state, s.frames_queued, s.frames_done), (RenderState::Cancelled, 0, 0));
        assert_eq!(on(&engine, |c| c.farm_metrics().pending_frames), 0);
    }
}
