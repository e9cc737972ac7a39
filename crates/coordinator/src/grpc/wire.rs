//! The gRPC door's conversions: the core's answers (jobs, statuses, worker rows) as protobuf
//! messages. A request's own conversion (settings, setup, submission) is `tessera-request`'s.

use crate::model::{FrameDone, Job, RenderInfo, RenderState, WorkerStatus};
use tessera_proto::v1;
use tessera_request::wire::tile_to_wire;

pub fn job_to_wire(j: &Job) -> v1::Job {
    v1::Job {
        lease_id: j.lease_id.to_string(),
        render_id: j.render_id.to_string(),
        scene_hash: j.scene_hash.clone(),
        settings: Some(j.setup.to_wire()),
        tile: Some(tile_to_wire(j.tile)),
        first_pass: j.first_pass,
        pass_count: j.pass_count,
        pass_spp: j.pass_spp,
        spp: j.spp,
        lease_seconds: j.lease_seconds,
    }
}

pub fn state_to_wire(s: RenderState) -> v1::RenderState {
    match s {
        RenderState::Running => v1::RenderState::Running,
        RenderState::Done => v1::RenderState::Done,
        RenderState::Cancelled => v1::RenderState::Cancelled,
        RenderState::Failed => v1::RenderState::Failed,
    }
}

pub fn info_to_wire(i: RenderInfo) -> v1::RenderStatus {
    v1::RenderStatus {
        render_id: i.render_id,
        scene_name: i.scene_name,
        state: state_to_wire(i.state) as i32,
        passes_done: i.passes_done,
        passes_total: i.passes_total,
        samples_done: i.samples_done,
        samples_per_second: i.samples_per_second,
        error_estimate: i.error_estimate,
        error_bound: i.error_bound,
        confidence: i.confidence as f32,
        eta_seconds: i.eta_seconds,
        no_workers: i.no_workers,
        priority: i.priority,
        paused: i.paused,
        placement: i.placement,
        no_worker_fits: i.no_worker_fits,
        submitted_at: i.submitted_at.unwrap_or(0.0),
        started_at: i.started_at.unwrap_or(0.0),
        ended_at: i.ended_at.unwrap_or(0.0),
        name: i.name,
        message: i.message,
        mean_spp: i.mean_spp,
        owner: i.owner,
        sequence_id: i.sequence_id,
        frame: i.frame,
        frames_total: i.frames_total,
        frames_done: i.frames_done,
        frames_running: i.frames_running,
        frames_queued: i.frames_queued,
        frames_failed: i.frames_failed,
        finished: i
            .finished
            .into_iter()
            .map(|FrameDone { frame, render_id }| v1::FrameDone { frame, render_id })
            .collect(),
        previewed: i
            .previewed
            .into_iter()
            .map(|FrameDone { frame, render_id }| v1::FrameDone { frame, render_id })
            .collect(),
        quote: i.quote.map(|f| v1::RenderQuote {
            samples: f.samples,
            samples_low: f.samples_low,
            samples_high: f.samples_high,
            samples_done: f.samples_done,
            tiles_judged: f.tiles_judged as u32,
            tiles: f.tiles as u32,
            workers: f.workers as u32,
            threads: f.threads,
            samples_per_second: f.samples_per_second,
        }),
    }
}

pub fn worker_to_wire(w: WorkerStatus) -> v1::WorkerStatus {
    v1::WorkerStatus {
        worker_id: w.worker_id,
        name: w.name,
        threads: w.threads,
        samples_per_second: w.samples_per_second,
        leases: w.leases,
        seconds_since_seen: w.seconds_since_seen,
        host: w.host,
        results: w.results,
        failures: w.failures,
        render_ids: w.renders.iter().take(WORKER_RENDERS_LISTED).map(i64::to_string).collect(),
        render_count: w.renders.len().try_into().unwrap_or(u32::MAX),
        state: w.state.name().to_string(),
        blocked_from: w.blocked_from.iter().take(WORKER_RENDERS_LISTED).map(i64::to_string).collect(),
        pool: w.pool,
        tags: w.tags.iter().map(ToString::to_string).collect(),
    }
}

/// The most render ids one worker's row carries: a worker may hold jobs of every running render,
/// and a page of such rows must stay far below a gRPC message's 4 MiB.
pub const WORKER_RENDERS_LISTED: usize = 64;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_worker_row_lists_at_most_64_renders_and_counts_them_all() {
        let status = |renders: Vec<i64>| WorkerStatus {
            worker_id: "w".into(),
            name: "n".into(),
            threads: 2,
            samples_per_second: 1e6,
            leases: renders.len() as u32,
            seconds_since_seen: 0.5,
            host: "10.0.0.7".into(),
            results: 12,
            failures: 1,
            renders,
            state: crate::model::WorkerState::Busy,
            blocked_from: vec![3],
            pool: String::new(),
            tags: Vec::new(),
        };
        let wire = worker_to_wire(status((1..=1000).collect()));
        assert_eq!(wire.render_ids.len(), WORKER_RENDERS_LISTED);
        assert_eq!((wire.render_ids[0].as_str(), wire.render_ids[63].as_str()), ("1", "64"));
        assert_eq!(wire.render_count, 1000);
        assert_eq!((wire.host.as_str(), wire.results, wire.failures), ("10.0.0.7", 12, 1));
        let wire = worker_to_wire(status(vec![3, 9]));
        assert_eq!((wire.render_ids, wire.render_count), (vec!["3".to_string(), "9".to_string()], 2));
    }
}
