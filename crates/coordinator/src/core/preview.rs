//! Previews first (`submit --frames 1-240 --preview-every 8 --preview-spp 16`, or
//! `--preview-target-error 0.05`): while a sequence previews, the lease table hands out only
//! its preview frames' first passes (up to the preview's samples; by error, any pass until the
//! frame's error estimate is down to the target, then none) and none of its other frames'
//! ([`crate::leases::LeaseTable::set_cap`]); each preview frame's image is written as
//! `<id>.preview.exr` once its film holds its preview; when every preview frame has its
//! preview (or stopped), the caps are
//! lifted and every frame goes on to its full samples. The caps change only the order in which
//! passes are handed out, never which passes make a frame: its image is the same bits as
//! without previews. The phase is not stored: it is worked out again from the merged passes
//! when the coordinator starts.

use super::{Core, CoreError, Target};
use crate::core::Finished;
use crate::model::RenderState;
use std::collections::BTreeSet;
use std::path::PathBuf;

/// A sequence previewing: how far a preview goes, and its preview frames still without one.
#[derive(Clone, Debug, Default)]
pub(super) struct Previewing {
    size: Size,
    waiting: BTreeSet<i64>,
}

/// How far a preview goes: its first passes of every tile, or until the frame's relative error
/// (as `status` estimates it, with every tile sampled) is down to a target.
#[derive(Clone, Copy, Debug)]
enum Size {
    Passes(u32),
    Error(f64),
}

impl Default for Size {
    fn default() -> Self {
        Size::Passes(1)
    }
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
        let size = match first.stored.preview_target {
            e if e > 0.0 => Size::Error(e),
            _ => Size::Passes(spp.div_ceil(pass_spp.max(1)).max(1)),
        };
        let previews: Vec<i64> = frames.iter().copied().filter(|&id| (id - seq) % every as i64 == 0).collect();
        let waiting: BTreeSet<i64> =
            previews.iter().copied().filter(|&id| self.running(id) && !self.has_preview(id, size)).collect();
        if waiting.is_empty() {
            return;
        }
        for &id in &frames {
            // A preview by error has no cap until it is reached; then it holds.
            let cap = match size {
                _ if !previews.contains(&id) => Some(0),
                Size::Passes(passes) => Some(passes),
                Size::Error(_) if waiting.contains(&id) => None,
                Size::Error(_) => Some(0),
            };
            self.leases.set_cap(id as u64, cap);
        }
        self.previewing.insert(seq, Previewing { size, waiting });
    }

    fn running(&self, id: i64) -> bool {
        self.renders.get(&id).is_some_and(|r| r.state == RenderState::Running && !r.writing)
    }

    /// Whether frame `id`'s film holds its preview: the first passes of every tile (or all a
    /// tile has), or samples in every tile and a relative error down to the target.
    fn has_preview(&self, id: i64, size: Size) -> bool {
        let Some(r) = self.renders.get(&id) else { return false };
        match size {
            Size::Passes(passes) => {
                r.film_passes.iter().zip(&r.budget).all(|(&merged, &budget)| merged >= passes.min(budget))
            }
            Size::Error(target) => {
                r.film_passes.iter().all(|&merged| merged > 0) && super::error_estimate(&r.film, 0.0).estimate <= target
            }
        }
    }

    /// After a merge into frame `id`, or its stop: once it has its preview (or stopped), its
    /// preview image is queued for writing ([`Core::take_previews`]), and when it was the
    /// sequence's last preview to come, every frame goes on to its full samples.
    pub(super) fn preview_progress(&mut self, id: i64) {
        let Some(seq) = self.renders.get(&id).map(|r| r.stored.sequence).filter(|&s| s != 0) else { return };
        let Some(p) = self.previewing.get(&seq).filter(|p| p.waiting.contains(&id)) else { return };
        let size = p.size;
        let stopped = !self.running(id);
        if !stopped && !self.has_preview(id, size) {
            return;
        }
        if let Size::Error(_) = size {
            // It has its preview: nothing more of it until every preview frame has one.
            self.leases.set_cap(id as u64, Some(0));
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
            let reached = match size {
                Size::Passes(passes) => {
                    format!("{} spp", passes * self.renders.get(&id).map_or(1, |r| r.plan.pass_spp))
                }
                Size::Error(e) => format!("error {}", e as f32),
            };
            self.note_target(Target::Sequence(seq), format!("previews done ({reached}): every frame goes on"));
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
        self.frames_in(seq, |t| &t.previewed, from, limit)
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
