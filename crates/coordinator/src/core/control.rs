//! Farm control: cancelling a render or a sequence, retrying a failed or cancelled one (checked
//! under the lock, its stored results read outside it, then put to work: what it merged is
//! kept), refining a finished one to more samples or a lower target error (the same way),
//! pausing, resuming and reprioritising one, and what a target stands for and who owns it.

use super::{CANCELLED, Core, CoreError, FAILED, Prepared, RUNNING, Resumed, Target};
use crate::model::RenderState;
use crate::store::{StoredRender, Write};

/// A change to a running render or sequence after submit; `None` leaves a setting as it is.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Steer {
    pub priority: Option<i32>,
    pub paused: Option<bool>,
    /// With a pause: hand its jobs in flight back at once (their results are ignored, and the
    /// passes rendered again after the resume, to the same bits), instead of letting them
    /// finish and merge.
    pub now: bool,
}

/// What `tessera refine` asks of a finished render: more samples per pixel, a lower target
/// error (an adaptive render's), or both; `None` keeps the render's own.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Refinement {
    pub spp: Option<u32>,
    pub target_error: Option<f64>,
}

impl Core {
    /// Steers a queued or running render, or a whole sequence (a frame alone is refused: its
    /// sequence is scheduled as one): it takes effect at the next lease, is stored, and is
    /// noted in the render's log as done by `who`.
    pub fn steer(&mut self, target: Target, steer: Steer, who: &str) -> Result<(), CoreError> {
        let group = match target {
            Target::Sequence(seq) => seq,
            Target::Render(id) => match self.renders.get(&id).map(|r| r.stored.sequence) {
                Some(seq) if seq != 0 => {
                    return Err(CoreError::Invalid(format!(
                        "render {id} is a frame of sequence s{seq}: pause, resume or reprioritise the sequence (s{seq})"
                    )));
                }
                _ => id,
            },
        };
        if let Some(p) = steer.priority {
            tessera_request::limits::check_priority(p).map_err(CoreError::Invalid)?;
        }
        let Some((priority, paused)) = self.leases.steering(group as u64) else {
            return Err(match self.status_of(target) {
                None => CoreError::NotFound(format!("no render {target}")),
                Some(info) => CoreError::Invalid(format!(
                    "{target} is {}: only a queued or running render can be paused, resumed or reprioritised",
                    info.state.name()
                )),
            });
        };
        let (priority, paused) = (steer.priority.unwrap_or(priority), steer.paused.unwrap_or(paused));
        self.leases.steer(group as u64, Some(priority), Some(paused));
        let released = if paused && steer.now { self.leases.release_group(group as u64).len() } else { 0 };
        self.write(Write::Steer { target: group, priority, paused });
        let by = if who.is_empty() { String::new() } else { format!(" by {who}") };
        let mut said = Vec::new();
        if let Some(p) = steer.priority {
            said.push(format!("priority set to {p}{by}"));
        }
        match steer.paused {
            Some(true) if released > 0 => said.push(format!("paused{by}, {released} job(s) in flight handed back")),
            Some(true) => said.push(format!("paused{by}")),
            Some(false) => said.push(format!("resumed{by}")),
            None => {}
        }
        // Each frame keeps its steering, so that one retried later is put back as steered.
        for id in self.members(target) {
            if let Some(r) = self.renders.get_mut(&id) {
                (r.stored.priority, r.stored.paused) = (priority, paused);
            }
            if let Some(stored) = self.failed.get_mut(&id) {
                (stored.priority, stored.paused) = (priority, paused);
            }
        }
        for line in said {
            tracing::info!(render = %target, "render {target} {line}");
            self.note_target(target, line);
        }
        Ok(())
    }

    /// Sets the owners' weights in the fair share (an owner not named weighs 1).
    pub fn set_weights(&mut self, weights: std::collections::HashMap<String, f64>) {
        self.leases.set_weights(weights);
    }

    /// Cancels a running render: its leases are dropped, and what it merged is kept in the store.
    pub fn cancel(&mut self, id: i64) -> Result<(), CoreError> {
        if self.failed.contains_key(&id) {
            return Ok(());
        }
        let r = self.renders.get_mut(&id).ok_or_else(|| CoreError::NotFound(format!("no render {id}")))?;
        if r.state == RenderState::Running {
            r.state = RenderState::Cancelled;
            self.note(id, "cancelled");
            self.leases.remove_render(id as u64);
            self.drop_checks(id);
            self.write(Write::State { render: id, state: CANCELLED, message: String::new() });
            self.collect_scenes();
            self.recount(id);
            self.preview_progress(id);
            self.tell_end(id);
        }
        Ok(())
    }

    /// Checks that render `id` may be retried (it failed or was cancelled, and stores nothing any
    /// more) and prepares it; its results are then read ([`Prepared::read`]) and
    /// [`Core::end_retry`] puts it to work. Until then it stays stopped, and another retry is
    /// refused.
    pub fn begin_retry(&mut self, id: i64) -> Result<Prepared, CoreError> {
        let stored = match (self.failed.get(&id), self.renders.get(&id)) {
            _ if self.retrying.contains(&id) => {
                return Err(CoreError::NotReady(format!("render {id} is being retried")));
            }
            (Some(stored), _) => stored.clone(),
            (None, Some(r)) if r.state.stopped() && r.committing > 0 => {
                // Its film is rebuilt from the store: results still on their way there would be
                // missed by it, and stored again later.
                return Err(CoreError::NotReady(format!(
                    "render {id} is still storing {} result(s): retry in a moment",
                    r.committing
                )));
            }
            (None, Some(r)) if r.state.stopped() => r.stored.clone(),
            (None, Some(r)) => {
                let state = r.state.name();
                return Err(CoreError::Invalid(format!(
                    "render {id} is {state}: only a failed or cancelled render can be retried"
                )));
            }
            (None, None) => return Err(CoreError::NotFound(format!("no render {id}"))),
        };
        let stored = StoredRender { state: RUNNING.into(), message: String::new(), ..stored };
        // Its own film (if it still holds one) is about to be replaced: not counted against it.
        let prepared = self.prepare(stored)?;
        self.retrying.insert(id);
        Ok(prepared)
    }

    /// The renders a refinement applies to ([`Core::begin_refine`]): a finished render, or every
    /// frame of a sequence, which must all have finished.
    pub fn refine_members(&self, target: Target) -> Result<Vec<i64>, CoreError> {
        let members = self.members(target);
        if members.is_empty() {
            return Err(CoreError::NotFound(format!("no render {target}")));
        }
        let whole = if let Target::Sequence(_) = target { " (a sequence, once every frame has)" } else { "" };
        for &id in &members {
            self.refinable(id, whole)?;
        }
        Ok(members)
    }

    /// Finished render `id`'s runtime, or why it cannot be refined (`whole` ends the message).
    fn refinable(&self, id: i64, whole: &str) -> Result<&super::RenderRuntime, CoreError> {
        let state = match self.renders.get(&id) {
            Some(r) if r.state == RenderState::Done && !r.writing => return Ok(r),
            Some(r) if r.state == RenderState::Done => "still writing its image",
            Some(r) => r.state.name(),
            None if self.failed.contains_key(&id) => "failed",
            None => return Err(CoreError::NotFound(format!("no render {id}"))),
        };
        Err(CoreError::Invalid(format!("render {id} is {state}: only a finished render can be refined{whole}")))
    }

    /// Checks that finished render `id` may be refined as `to` asks, and prepares it with its
    /// new quality: the change and its running state are stored (before its results are read,
    /// so that a restart resumes it refined), its results are read ([`Prepared::read`]) and
    /// [`Core::end_retry`] puts it to work. Only the passes the new quality adds are rendered:
    /// a render submitted with it would have merged every pass this one did (more samples
    /// extend each tile's passes; a lower target error continues each tile's rounds at least as
    /// long), so the image is the same bits.
    pub fn begin_refine(&mut self, id: i64, to: Refinement) -> Result<Prepared, CoreError> {
        if self.retrying.contains(&id) {
            return Err(CoreError::NotReady(format!("render {id} is being retried or refined")));
        }
        let old = &self.refinable(id, "")?.stored;
        let spp = to.spp.unwrap_or(old.spp);
        let target_error = to.target_error.unwrap_or(old.target_error);
        if spp < old.spp {
            return Err(CoreError::Invalid(format!(
                "render {id} has {} spp: refining adds samples (--spp {} or more)",
                old.spp, old.spp
            )));
        }
        if spp > self.config.max_spp {
            return Err(CoreError::Limit(format!(
                "spp {spp} is over this coordinator's limit of {}",
                self.config.max_spp
            )));
        }
        if spp != old.spp && old.spp % old.pass_spp != 0 {
            return Err(CoreError::Invalid(format!(
                "render {id}'s {} spp end in a part of a {}-spp pass, which cannot be extended bit for bit: submit it again",
                old.spp, old.pass_spp
            )));
        }
        match to.target_error {
            Some(_) if old.target_error <= 0.0 => {
                return Err(CoreError::Invalid(format!(
                    "render {id} has a fixed sample count: refine it with more spp, not a target error"
                )));
            }
            Some(e) if !(e > 0.0 && e <= old.target_error) => {
                return Err(CoreError::Invalid(format!(
                    "render {id}'s target error is {}: refining lowers it (a target above 0, at most that)",
                    old.target_error
                )));
            }
            _ => {}
        }
        if spp == old.spp && target_error == old.target_error {
            return Err(CoreError::Invalid(format!("render {id} already has that quality: nothing to refine")));
        }
        let stored = StoredRender { state: RUNNING.into(), message: String::new(), spp, target_error, ..old.clone() };
        let prepared = self.prepare(stored)?;
        self.write(Write::Quality { render: id, spp, target_error });
        self.write(Write::State { render: id, state: RUNNING, message: String::new() });
        self.retrying.insert(id);
        let error = if target_error > 0.0 { format!(", target error {target_error}") } else { String::new() };
        self.note(id, format!("refined to {spp} spp{error}: rendering only the passes that adds"));
        Ok(prepared)
    }

    /// A refinement whose change could not be stored: the render stays as it was.
    pub fn abandon_refine(&mut self, id: i64) {
        self.retrying.remove(&id);
    }

    /// Puts a retried render to work with what was read of it, or marks it failed again saying
    /// why it could not be read.
    pub fn end_retry(&mut self, id: i64, read: Result<Resumed, CoreError>) -> Result<(), CoreError> {
        self.retrying.remove(&id);
        let stored = self.failed.remove(&id).or_else(|| self.renders.remove(&id).map(|r| r.stored));
        self.recount(id);
        self.attempts.retain(|&(render, _, _), _| render != id);
        self.worker_failures.remove(&id);
        match read {
            Ok(resumed) => {
                self.write(Write::State { render: id, state: RUNNING, message: String::new() });
                self.install(resumed);
                tracing::info!(render = id, "render {id} retried");
                self.note(id, "retried: queued again, keeping what it merged");
                Ok(())
            }
            Err(e) => {
                let message = format!("could not be resumed: {e}");
                if let Some(stored) = stored {
                    self.unresumable(stored, message.clone());
                }
                Err(CoreError::Invalid(format!("render {id} {message}")))
            }
        }
    }

    /// The renders a target stands for: itself, or a sequence's frames.
    pub fn members(&self, target: Target) -> Vec<i64> {
        match target {
            Target::Render(id) => vec![id],
            Target::Sequence(seq) => self.sequences.get(&seq).cloned().unwrap_or_default(),
        }
    }

    /// Forgets a render or sequence just submitted whose rows could not be stored.
    pub fn forget(&mut self, target: Target) {
        for id in self.members(target) {
            self.leases.remove_render(id as u64);
            self.renders.remove(&id);
            self.failed.remove(&id);
            self.recount(id);
        }
        if let Target::Sequence(seq) = target {
            self.sequences.remove(&seq);
            self.counts.tallies.remove(&seq);
        }
    }

    /// Cancels a render, or every frame of a sequence.
    pub fn cancel_target(&mut self, target: Target) -> Result<(), CoreError> {
        for id in self.members(target) {
            self.cancel(id)?;
        }
        Ok(())
    }

    /// The renders a retry of `target` retries: the render, or a sequence's failed and
    /// cancelled frames.
    pub fn retry_members(&self, target: Target) -> Result<Vec<i64>, CoreError> {
        let Target::Sequence(_) = target else { return Ok(self.members(target)) };
        let stopped =
            |id: &i64| self.failed.contains_key(id) || self.renders.get(id).is_some_and(|r| r.state.stopped());
        let frames: Vec<i64> = self.members(target).into_iter().filter(stopped).collect();
        if frames.is_empty() {
            return Err(CoreError::Invalid(format!("sequence {target} has no failed or cancelled frames to retry")));
        }
        Ok(frames)
    }

    /// Who submitted a render or sequence; `None` if there is none.
    pub fn owner_of(&self, target: Target) -> Option<&str> {
        match target {
            Target::Render(id) => self.owner(id),
            Target::Sequence(seq) => self.sequences.get(&seq).and_then(|f| f.first()).and_then(|&id| self.owner(id)),
        }
    }

    /// Who submitted render `id` (empty without per-user tokens); `None` if there is no such render.
    pub fn owner(&self, id: i64) -> Option<&str> {
        self.renders
            .get(&id)
            .map(|r| r.stored.owner.as_str())
            .or_else(|| self.failed.get(&id).map(|s| s.owner.as_str()))
    }

    /// Scene `hash` is lost (its stored bytes no longer match the hash): every render still to
    /// finish that uses it fails, saying `why` (a retry puts it back to work once the scene is
    /// uploaded again). Returns the renders failed.
    pub fn scene_lost(&mut self, hash: &str, why: &str) -> Vec<i64> {
        let lost: Vec<i64> = self
            .renders
            .iter()
            .filter(|(_, r)| r.state == RenderState::Running && r.stored.scene_hash == hash)
            .map(|(&id, _)| id)
            .collect();
        for &id in &lost {
            self.fail_render(id, format!("its scene is lost: {why}"));
        }
        lost
    }

    /// Fails render `id`, saying `message`: its leases and checks are dropped, and a retry puts
    /// it back to work.
    pub(super) fn fail_render(&mut self, id: i64, message: String) {
        tracing::error!(render = id, "render {id} failed: {message}");
        self.note(id, format!("failed: {message}"));
        self.take_out_of_work(id, message);
        self.tell_end(id);
    }

    /// Takes render `id` out of work, failed with `message` in the store: what failing it and
    /// reopening it for a blocked worker's results share. Neither notes nor notifies.
    pub(super) fn take_out_of_work(&mut self, id: i64, message: String) {
        self.leases.remove_render(id as u64);
        self.drop_checks(id);
        if let Some(r) = self.renders.get_mut(&id) {
            r.state = RenderState::Failed;
            r.message = message.clone();
        }
        self.write(Write::State { render: id, state: FAILED, message });
        self.recount(id);
        self.preview_progress(id);
    }

    /// Forgets the checks render `id` waits for (it left the running state).
    fn drop_checks(&mut self, id: i64) {
        let keys: Vec<_> = self.checks_of(id).copied().collect();
        for k in keys {
            self.checks.remove(&k);
        }
    }
}
