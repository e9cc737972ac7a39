//! Verified workers (`core/verify.rs`): test workers that answer honestly or lie, driving the
//! engine as real workers would.

use super::{fresh_dir, furnace, hash, on, request, state, straight, submitted_as};
use crate::core::{CoreConfig, CoreError, Outcome, REOPENED, RenderPlan};
use crate::engine::{Engine, EngineError};
use crate::model::{Job, Offer, RenderState};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tessera_proto::sums::encode_tile_sums;
use tessera_render::render_tile;

/// How a test worker answers: honestly, or with plausible wrong sums (the right tile and
/// counts, values in bounds: one pixel's red sum off by `n`).
#[derive(Clone, Copy, PartialEq)]
enum Answer {
    Honest,
    Lie(u128),
}

/// Leases a job to `worker` and answers it; `Ok(false)` when there was no work.
async fn serve(
    engine: &Arc<Engine>,
    scene: &tessera_render::Scene,
    worker: &str,
    answer: Answer,
) -> Result<bool, EngineError> {
    let Some(job): Option<Job> = engine.lease(&Offer::plain(worker), None, Duration::ZERO).await? else {
        return Ok(false);
    };
    let samples = RenderPlan::new(64, 16, 16, job.spp, job.pass_spp).samples(job.first_pass, job.pass_count);
    let mut sums = render_tile(scene, &job.setup.settings, job.tile, samples).unwrap();
    if let Answer::Lie(by) = answer {
        sums.pixels[0].sum[0] = sums.pixels[0].sum[0].wrapping_add(by as i128);
    }
    let outcome = engine.complete(worker, &job.lease_id.to_string(), encode_tile_sums(&sums)).await?;
    Ok(outcome == Outcome::Merged)
}

/// Works the farm `workers` until render `id` leaves the running state (it shows as running
/// while a blocked worker's results are rendered again, and never as failed); blocked workers
/// are left out once refused.
async fn work_until_done(engine: &Arc<Engine>, id: i64, workers: &[(&str, Answer)]) -> Vec<String> {
    let scene = furnace();
    let mut refused = Vec::new();
    let start = Instant::now();
    loop {
        let mut served = false;
        for &(w, answer) in workers {
            if refused.iter().any(|r| r == w) {
                continue;
            }
            match serve(engine, &scene, w, answer).await {
                Ok(s) => served |= s,
                Err(EngineError::Core(CoreError::Refused(_))) => refused.push(w.to_string()),
                Err(e) => panic!("{w}: {e}"),
            }
        }
        // Reopened, it is failed inside the core until its retry, and shown running throughout.
        let reopened = on(engine, |c| c.renders[&id].message.starts_with(REOPENED));
        let shown = state(engine, id);
        assert!(!reopened || shown == RenderState::Running, "render {id}, reopened, showed as {shown:?}");
        if shown != RenderState::Running {
            return refused;
        }
        assert!(start.elapsed() < Duration::from_secs(60), "the render did not finish");
        if !served {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    }
}

fn verifying(dir: &std::path::Path, fraction: f64) -> CoreConfig {
    CoreConfig { verify: fraction, ..CoreConfig::new(dir.to_path_buf()) }
}

/// `--verify 1`: a worker that returns plausible wrong sums is caught by a third worker,
/// blocked for the farm (it is refused jobs, and stays so after a restart), its results are
/// deleted and rendered again, and the image is the same file as with honest workers alone.
/// The test render is adaptive, so its rounds are replayed from the honest results.
#[tokio::test]
async fn a_lying_worker_is_caught_blocked_and_its_results_rendered_again() {
    let dir = fresh_dir("liar");
    let (engine, id) = submitted_as(verifying(dir.path(), 1.0), request(&hash())).await;
    let scene = furnace();
    // The liar's results are merged first (no one else is working yet), then honest
    // workers check them.
    for _ in 0..3 {
        assert!(serve(&engine, &scene, "liar", Answer::Lie(1 << 20)).await.unwrap());
    }
    let workers = [("a", Answer::Honest), ("b", Answer::Honest), ("liar", Answer::Lie(1 << 20))];
    let refused = work_until_done(&engine, id, &workers).await;
    assert_eq!(state(&engine, id), RenderState::Done);
    assert_eq!(refused, vec!["liar".to_string()], "the liar is refused jobs");
    let metrics = on(&engine, |c| c.farm_metrics());
    assert!(metrics.counters.results_disputed >= 1);
    assert_eq!(metrics.workers_blocked, 1);
    assert_eq!(metrics.checks_pending, 0);
    // The same render straight through by one honest worker, unchecked: the same bits.
    let (straight, id2, straight_dir) = straight(request(&hash())).await;
    assert_eq!(straight.image(id2).await.unwrap(), engine.image(id).await.unwrap(), "images differ");
    // Every pass is stored once, and none of the liar's.
    let db = rusqlite::Connection::open(dir.path().join("tessera.db")).unwrap();
    let count = |sql: &str| db.query_row(sql, [], |r| r.get::<_, i64>(0)).unwrap();
    assert_eq!(count("SELECT COUNT(*) FROM results WHERE worker = 'liar'"), 0);
    assert_eq!(count("SELECT COUNT(*) FROM results WHERE unchecked = 1"), 0);
    let straight_db = rusqlite::Connection::open(straight_dir.path().join("tessera.db")).unwrap();
    let passes = "SELECT SUM(pass_count) FROM results";
    let straight_passes = straight_db.query_row(passes, [], |r| r.get::<_, i64>(0)).unwrap();
    assert_eq!(count(passes), straight_passes, "passes stored");
    // The block outlives a restart.
    drop(engine);
    let engine = Engine::open(verifying(dir.path(), 1.0)).unwrap();
    let again = engine.lease(&Offer::plain("liar"), None, Duration::ZERO).await;
    assert!(matches!(again, Err(EngineError::Core(CoreError::Refused(_)))), "{:?}", again.map(|j| j.is_some()));
}

/// The liar checks an honest worker's result: its wrong check is outvoted, it is blocked,
/// and the honest result stands.
#[tokio::test]
async fn a_lying_checker_is_outvoted() {
    let dir = fresh_dir("liar-checker");
    let (engine, id) = submitted_as(verifying(dir.path(), 1.0), request(&hash())).await;
    let workers = [("a", Answer::Honest), ("liar", Answer::Lie(3)), ("b", Answer::Honest)];
    let refused = work_until_done(&engine, id, &workers).await;
    assert_eq!(state(&engine, id), RenderState::Done);
    assert_eq!(refused, vec!["liar".to_string()]);
    let (straight, id2, _straight_dir) = straight(request(&hash())).await;
    assert_eq!(straight.image(id2).await.unwrap(), engine.image(id).await.unwrap(), "images differ");
}

/// Three workers, three answers: no one can be told apart as the faulty one, so the render
/// fails saying so, and no one is blocked.
#[tokio::test]
async fn three_different_answers_fail_the_render() {
    let dir = fresh_dir("three-answers");
    let (engine, id) = submitted_as(verifying(dir.path(), 1.0), request(&hash())).await;
    let workers = [("a", Answer::Lie(1)), ("b", Answer::Lie(2)), ("c", Answer::Honest)];
    work_until_done(&engine, id, &workers).await;
    assert_eq!(state(&engine, id), RenderState::Failed);
    let message = on(&engine, |c| c.renders[&id].message.clone());
    assert!(message.contains("three different sums"), "{message}");
    assert_eq!(on(&engine, |c| c.blocked_workers()), 0);
}

/// With one worker a checked render waits at its end for a second, and says so.
#[tokio::test]
async fn a_check_waits_for_a_second_worker() {
    let dir = fresh_dir("one-worker");
    let (engine, id) = submitted_as(verifying(dir.path(), 1.0), request(&hash())).await;
    let scene = furnace();
    while serve(&engine, &scene, "a", Answer::Honest).await.unwrap() {}
    assert_eq!(state(&engine, id), RenderState::Running);
    let message = on(&engine, |c| c.renders[&id].message.clone());
    assert!(message.contains("to be checked by another worker"), "{message}");
    work_until_done(&engine, id, &[("b", Answer::Honest)]).await;
    assert_eq!(state(&engine, id), RenderState::Done);
}

/// A checker that hangs up (or dies) as soon as its result is sent: the coordinator still judges
/// the check, writes the image and marks the render done. (Its handler used to be dropped with
/// the call, leaving the image written and the render running for ever: the chaos test caught
/// it.) Every check here is answered by a call dropped after its first poll.
#[tokio::test]
async fn a_checker_that_hangs_up_still_finishes_the_render() {
    let dir = fresh_dir("hang-up");
    let (engine, id) = submitted_as(verifying(dir.path(), 1.0), request(&hash())).await;
    let scene = furnace();
    while serve(&engine, &scene, "a", Answer::Honest).await.unwrap() {}
    let start = Instant::now();
    while state(&engine, id) == RenderState::Running {
        assert!(start.elapsed() < Duration::from_secs(60), "the render did not finish");
        let Some(job) = engine.lease(&Offer::plain("b"), None, Duration::ZERO).await.unwrap() else {
            tokio::time::sleep(Duration::from_millis(5)).await;
            continue;
        };
        let samples = RenderPlan::new(64, 16, 16, job.spp, job.pass_spp).samples(job.first_pass, job.pass_count);
        let sums = render_tile(&scene, &job.setup.settings, job.tile, samples).unwrap();
        let lease = job.lease_id.to_string();
        let call = engine.complete("b", &lease, encode_tile_sums(&sums));
        // One poll, then the call is gone, as when the worker's connection drops.
        let mut call = std::pin::pin!(call);
        tokio::select! {
            biased;
            _ = call.as_mut() => {}
            _ = async {} => {}
        }
    }
    assert_eq!(state(&engine, id), RenderState::Done);
    assert!(engine.image(id).await.is_ok(), "the image is there");
}

/// `--verify 0.25` checks about a quarter of the jobs, the same ones whatever the order.
#[test]
fn the_sampled_fraction_is_about_the_one_asked_for() {
    let dir = fresh_dir("fraction");
    let engine = Engine::open(verifying(dir.path(), 0.25)).unwrap();
    let picked = on(&engine, |c| (0..4000u32).filter(|&i| c.sampled(1, i % 40, i / 40)).count());
    // Binomial(4000, 0.25): sd 27; 5 sd either side.
    assert!((865..=1135).contains(&picked), "{picked} of 4000");
    let again = on(&engine, |c| (0..4000u32).filter(|&i| c.sampled(1, i % 40, i / 40)).count());
    assert_eq!(picked, again);
}

/// A render reopened for a blocked worker's results is failed inside the core only until its
/// retry: its status shows it running, saying why, and its log does not call it failed.
#[tokio::test]
async fn a_reopened_render_shows_as_running_until_its_retry() {
    let dir = fresh_dir("reopened");
    let (engine, id) = submitted_as(CoreConfig::new(dir.path().to_path_buf()), request(&hash())).await;
    assert!(on(&engine, |c| c.reopen(id, "liar")));
    assert_eq!(on(&engine, |c| c.renders[&id].state), RenderState::Failed, "out of work inside the core");
    let status = on(&engine, |c| c.status(id).unwrap());
    assert_eq!(status.state, RenderState::Running);
    assert!(status.message.starts_with(REOPENED), "{}", status.message);
    assert!(on(&engine, |c| c.take_ended()).is_empty(), "nobody is told it ended");
}
