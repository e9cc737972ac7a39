//! Previews first (`submit --frames 1-240 --preview-every 8 --preview-spp 16`): while a
//! sequence previews, the lease table hands out only its preview frames' first passes (up to
//! the preview's samples) and none of its other frames' ([`crate::leases::LeaseTable::set_cap`]);
//! each preview frame's image is written as `<id>.preview.exr` once its film holds the
//! preview's passes; when every preview frame has its preview (or stopped), the caps are
//! lifted and every frame goes on to its full samples. The caps change only the order in which
//! passes are handed out, never which passes make a frame: its image is the same bits as
//! without previews. The phase is not stored: it is worked out again from the merged passes
//! when the coordinator starts.

use super::{Core, CoreError, Target};
use crate::core::Finished;
use crate::model::RenderState;
use std::collections::BTreeSet;
use std::path::PathBuf;

/// A sequence previewing: the passes of a preview, and its preview frames still without one.
#[derive(Clone, Debug, Default)]
pub(super) struct Previewing {
    passes: u32,
    waiting: BTreeSet<i64>,
}

impl Core {
    /// Starts sequence `seq`'s previews if it asked for them and some preview frame still
    /// lacks its preview (at submit, and again when the coordinator starts).
    pub(super) fn begin_previews(&mut self, seq: i64) {
        let frames = self.sequences.get(&seq).cloned().unwrap_or_default();
        let Some(first) = frames.first().and_then(|id| self.renders.get(id)) else { return };
        let (every, spp, pass_spp) = (first.stored.preview_every, first.stored.preview_spp, first.plan.pass_spp);
        if every == 0 {
            return;
        }
        let passes = spp.div_ceil(pass_spp.max(1)).max(1);
        let previews: Vec<i64> = frames.iter().copied().filter(|&id| (id - seq) % every as i64 == 0).collect();
        let waiting: BTreeSet<i64> =
            previews.iter().copied().filter(|&id| self.running(id) && !self.has_preview(id, passes)).collect();
        if waiting.is_empty() {
            return;
        }
        for &id in &frames {
            let cap = if previews.contains(&id) { passes } else { 0 };
            self.leases.set_cap(id as u64, Some(cap));
        }
        self.previewing.insert(seq, Previewing { passes, waiting });
    }

    fn running(&self, id: i64) -> bool {
        self.renders.get(&id).is_some_and(|r| r.state == RenderState::Running && !r.writing)
    }

    /// Whether frame `id`'s film holds the first `passes` passes of every tile (or all a tile has).
    fn has_preview(&self, id: i64, passes: u32) -> bool {
        self.renders
            .get(&id)
            .is_some_and(|r| r.film_passes.iter().zip(&r.budget).all(|(&merged, &budget)| merged >= passes.min(budget)))
    }

    /// After a merge into frame `id`, or its stop: once it has its preview (or stopped), its
    /// preview image is queued for writing ([`Core::take_previews`]), and when it was the
    /// sequence's last preview to come, every frame goes on to its full samples.
    pub(super) fn preview_progress(&mut self, id: i64) {
        let Some(seq) = self.renders.get(&id).map(|r| r.stored.sequence).filter(|&s| s != 0) else { return };
        let Some(p) = self.previewing.get(&seq).filter(|p| p.waiting.contains(&id)) else { return };
        let passes = p.passes;
        let stopped = !self.running(id);
        if !stopped && !self.has_preview(id, passes) {
            return;
        }
        if let Some(p) = self.previewing.get_mut(&seq) {
            p.waiting.remove(&id);
        }
        if !stopped && let Some(r) = self.renders.get(&id) {
            let metadata = r.setup.header(&r.stored.scene_name, &r.stored.scene_hash, r.stored.spp, r.film.dropped());
            let film = r.film.clone();
            let (transparent, path) = (r.setup.settings.transparent, self.preview_path(id));
            self.previews.push(Finished::new(id, film, transparent, metadata, path));
        }
        if self.previewing.get(&seq).is_some_and(|p| p.waiting.is_empty()) {
            self.previewing.remove(&seq);
            for id in self.members(Target::Sequence(seq)) {
                self.leases.set_cap(id as u64, None);
            }
            let spp = passes * self.renders.get(&id).map_or(1, |r| r.plan.pass_spp);
            self.note_target(Target::Sequence(seq), format!("previews done ({spp} spp): every frame goes on"));
        }
    }

    /// Preview images to write (outside the lock), each as it was when its frame had its
    /// preview.
    pub fn take_previews(&mut self) -> Vec<Finished> {
        std::mem::take(&mut self.previews)
    }

    /// Frame `id`'s preview image is written (or could not be): a watch of its sequence tells it.
    pub fn preview_written(&mut self, id: i64, written: Result<(), String>) {
        match written {
            Ok(()) => {
                let seq = self.renders.get(&id).map_or(0, |r| r.stored.sequence);
                if let Some(t) = self.counts.tallies.get_mut(&seq)
                    && !t.previewed.contains(&id)
                {
                    t.previewed.push(id);
                }
            }
            Err(e) => tracing::error!(render = id, "the preview image of render {id} could not be written: {e}"),
        }
    }

    /// The frames of sequence `seq` whose preview is written, from the `from`-th on (at most
    /// `limit`), and how many there are.
    pub fn previewed_frames(&self, seq: i64, from: usize, limit: usize) -> (Vec<crate::model::FrameDone>, usize) {
        let Some(t) = self.counts.tallies.get(&seq) else { return (Vec::new(), 0) };
        let frames = t
            .previewed
            .iter()
            .skip(from)
            .take(limit)
            .map(|&id| crate::model::FrameDone { frame: self.frame_of(id).unwrap_or(0), render_id: id.to_string() })
            .collect();
        (frames, t.previewed.len())
    }

    /// Where frame `id`'s preview image is (or will be).
    pub fn preview_path(&self, id: i64) -> PathBuf {
        self.config.data_dir.join("renders").join(format!("{id}.preview.exr"))
    }

    /// The preview frames of sequences with previews: their preview images, if on disk from
    /// before a restart, are told to watches ([`Core::preview_written`]).
    pub fn preview_frames(&self) -> Vec<(i64, PathBuf)> {
        let mut out = Vec::new();
        for (&seq, frames) in &self.sequences {
            let every = frames.first().and_then(|id| self.renders.get(id)).map_or(0, |r| r.stored.preview_every);
            if every > 0 {
                let previews = frames.iter().filter(|&&id| (id - seq) % every as i64 == 0);
                out.extend(previews.map(|&id| (id, self.preview_path(id))));
            }
        }
        out
    }

    /// Frame `id`'s preview image path, once written.
    pub fn written_preview(&self, id: i64) -> Result<PathBuf, CoreError> {
        let seq = self.renders.get(&id).map(|r| r.stored.sequence).unwrap_or(0);
        let written = self.counts.tallies.get(&seq).is_some_and(|t| t.previewed.contains(&id));
        if !written {
            return Err(CoreError::NotReady(format!("render {id} has no preview image (yet)")));
        }
        Ok(self.preview_path(id))
    }
}
