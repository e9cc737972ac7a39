//! The service edge: protobuf messages turned into the core's types (`model.rs`) and back, and
//! the bytes the store keeps a render's setup in (its protobuf encoding, which every database
//! written so far holds).

use crate::model::{EnvironmentMap, FrameDone, Job, Pose, RenderInfo, RenderState, Setup, Submission, WorkerStatus};
use prost::Message;
use tessera_proto::convert::{settings_from_wire, settings_to_wire, tile_to_wire};
use tessera_proto::v1;

/// A setup from the wire, its settings checked (`settings_from_wire`).
pub fn setup_from_wire(w: &v1::RenderSettings) -> Result<Setup, String> {
    let (settings, environment) = settings_from_wire(w).map_err(|e| e.to_string())?;
    Ok(Setup {
        settings,
        environment,
        pose: w.pose.as_ref().map(|p| Pose {
            animation: p.animation.clone(),
            time: p.time,
            frame: p.frame,
            fps: p.fps,
            sequence_seed: p.sequence_seed,
        }),
        environment_map: w.environment_map.as_ref().map(|m| EnvironmentMap {
            name: m.name.clone(),
            hash: m.hash.clone(),
            strength: m.strength,
            rotate_degrees: m.rotate_degrees,
        }),
        variant: (!w.variant.is_empty()).then(|| w.variant.clone()),
    })
}

pub fn setup_to_wire(s: &Setup) -> v1::RenderSettings {
    let mut w = settings_to_wire(&s.settings, s.environment);
    w.pose = s.pose.as_ref().map(|p| v1::Pose {
        animation: p.animation.clone(),
        time: p.time,
        frame: p.frame,
        fps: p.fps,
        sequence_seed: p.sequence_seed,
    });
    w.environment_map = s.environment_map.as_ref().map(|m| v1::EnvironmentMap {
        name: m.name.clone(),
        hash: m.hash.clone(),
        strength: m.strength,
        rotate_degrees: m.rotate_degrees,
    });
    w.variant = s.variant.clone().unwrap_or_default();
    w
}

/// The bytes the store keeps a render's setup in.
pub fn encode_setup(s: &Setup) -> Vec<u8> {
    setup_to_wire(s).encode_to_vec()
}

/// A setup from the bytes the store keeps.
pub fn decode_setup(bytes: &[u8]) -> Result<Setup, String> {
    setup_from_wire(&v1::RenderSettings::decode(bytes).map_err(|e| e.to_string())?)
}

pub fn submission_from_wire(r: &v1::SubmitRenderRequest) -> Result<Submission, String> {
    let settings = r.settings.as_ref().ok_or("no render settings")?;
    Ok(Submission {
        scene_hash: r.scene_hash.clone(),
        scene_name: r.scene_name.clone(),
        setup: setup_from_wire(settings)?,
        spp: r.spp,
        tile_size: r.tile_size,
        pass_spp: r.pass_spp,
        priority: r.priority,
        target_error: r.target_error,
        min_spp: r.min_spp,
        max_spp: r.max_spp,
        frames: r.frames.clone(),
        fps: r.fps,
    })
}

pub fn job_to_wire(j: &Job) -> v1::Job {
    v1::Job {
        lease_id: j.lease_id.to_string(),
        render_id: j.render_id.to_string(),
        scene_hash: j.scene_hash.clone(),
        settings: Some(setup_to_wire(&j.setup)),
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
        eta_seconds: i.eta_seconds,
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
    }
}

/// The most render ids one worker's row carries: a worker may hold jobs of every running render,
/// and a page of such rows must stay far below a gRPC message's 4 MiB.
pub const WORKER_RENDERS_LISTED: usize = 64;

#[cfg(test)]
mod tests {
    use super::*;
    use tessera_render::glam::Vec3;

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
        };
        let wire = worker_to_wire(status((1..=1000).collect()));
        assert_eq!(wire.render_ids.len(), WORKER_RENDERS_LISTED);
        assert_eq!((wire.render_ids[0].as_str(), wire.render_ids[63].as_str()), ("1", "64"));
        assert_eq!(wire.render_count, 1000);
        assert_eq!((wire.host.as_str(), wire.results, wire.failures), ("10.0.0.7", 12, 1));
        let wire = worker_to_wire(status(vec![3, 9]));
        assert_eq!((wire.render_ids, wire.render_count), (vec!["3".to_string(), "9".to_string()], 2));
    }

    #[test]
    fn a_setup_keeps_every_field_through_the_stored_encoding() {
        let setup = Setup {
            settings: tessera_render::RenderSettings {
                width: 31,
                height: 17,
                seed: 99,
                estimator: tessera_render::Estimator::Nee,
                density: tessera_render::Density::Brdf,
                sampler: tessera_render::SamplerKind::Sobol,
                termination: tessera_render::Termination::MaxBounces(6),
                camera: 2,
                color: tessera_render::ColorMode::Rgb,
                transparent: false,
                lights: tessera_render::LightSampler::Power,
            },
            environment: Vec3::new(0.25, 0.5, 2.0),
            pose: Some(Pose { animation: "=walk".into(), time: 1.25, frame: Some(30), fps: 24.0, sequence_seed: 7 }),
            environment_map: Some(EnvironmentMap {
                name: "sky.hdr".into(),
                hash: "ab".repeat(32),
                strength: 1.5,
                rotate_degrees: -90.0,
            }),
            variant: Some("midnight".into()),
        };
        assert_eq!(decode_setup(&encode_setup(&setup)).unwrap(), setup);
        assert!(decode_setup(b"\xff\xff").is_err(), "bytes that are no setup are refused");
    }
}
