//! The core's tests. They drive it through the [`Engine`], the path production takes: a result
//! is decoded, accepted under the lock, committed by the store's writer and merged; a restart is
//! an engine dropped (its writer commits what is queued) and opened again on the same directory.

use super::*;

mod quote;
mod refine;
mod stated;
mod steer;
mod verify;
mod workers;
use crate::engine::{Engine, EngineError};
use crate::model::{Adaptive, Frames, Job, Offer, Pose, Submission};
use crate::store::Store;
use std::sync::Arc;
use std::time::Duration;
use tessera_proto::sums::encode_tile_sums;
use tessera_render::glam::Vec3;
use tessera_render::plan::FrameList;
use tessera_render::{RenderSettings, Termination, TileSums, render_tile};

pub(crate) const SCENE: &[u8] = b"tessera-builtin:furnace?base=0.8&metallic=0.5&roughness=0.4";

fn settings() -> RenderSettings {
    RenderSettings { seed: 3, termination: Termination::MaxBounces(4), ..RenderSettings::new(64, 16) }
}

/// The test render: the furnace at 64 x 16 in 16-pixel tiles, up to 64 spp in passes of 4,
/// adaptive to a relative error of 0.02 from 4 spp.
pub(crate) fn request(hash: &str) -> Submission {
    Submission {
        scene_hash: hash.into(),
        scene_name: "furnace".into(),
        setup: Setup::new(settings(), Vec3::ONE),
        spp: 64,
        adaptive: Some(Adaptive { target_error: 0.02, min_spp: 4 }),
        tile_size: 16,
        pass_spp: 4,
        priority: 0,
        frames: None,
        name: String::new(),
        placement: Default::default(),
        notify: String::new(),
        paused: false,
        preview: None,
    }
}

pub(crate) fn hash() -> String {
    blake3::hash(SCENE).to_hex().to_string()
}

/// Leases a job to worker "w" (without waiting) and renders it for real, as a worker would;
/// `None` when there is no work. The result is not sent.
pub(crate) async fn render_job(engine: &Engine, scene: &tessera_render::Scene) -> Option<(Job, TileSums)> {
    let job = engine.lease(&Offer::plain("w"), None, Duration::ZERO).await.unwrap()?;
    let samples = RenderPlan::new(64, 16, 16, job.spp, job.pass_spp).samples(job.first_pass, job.pass_count);
    let sums = render_tile(scene, &job.setup.settings, job.tile, samples).unwrap();
    Some((job, sums))
}

/// Sends a rendered job's result as worker "w".
pub(crate) async fn complete(engine: &Arc<Engine>, job: &Job, sums: &TileSums) -> Result<Outcome, EngineError> {
    engine.complete("w", &job.lease_id.to_string(), encode_tile_sums(sums)).await
}

/// Works `jobs` jobs as a worker would, with real renders.
pub(crate) async fn work(engine: &Arc<Engine>, scene: &tessera_render::Scene, jobs: usize) {
    for _ in 0..jobs {
        let Some((job, sums)) = render_job(engine, scene).await else { return };
        assert_eq!(complete(engine, &job, &sums).await.unwrap(), Outcome::Merged);
    }
}

pub(crate) fn furnace() -> tessera_render::Scene {
    let options = tessera_scene::LoadOptions { environment: Some(Vec3::ONE), ..Default::default() };
    tessera_scene::load_packed(SCENE, "furnace", &options).unwrap().scene
}

/// An empty data directory under the temp dir, removed when dropped.
pub(crate) fn fresh_dir(name: &str) -> tempfile::TempDir {
    tempfile::Builder::new().prefix(&format!("tessera-core-{name}-")).tempdir().unwrap()
}

fn open(dir: &std::path::Path) -> Arc<Engine> {
    Engine::open(CoreConfig::new(dir.to_path_buf())).unwrap()
}

/// An engine with the furnace stored and `req` submitted.
pub(crate) async fn submitted_as(config: CoreConfig, req: Submission) -> (Arc<Engine>, i64) {
    let engine = Engine::open(config).unwrap();
    engine.put_scene("", hash(), SCENE.to_vec()).await.unwrap();
    let id = engine.submit(&crate::users::Identity::anyone(), req).await.unwrap().id();
    (engine, id)
}

/// An engine on `dir` with the furnace stored and the test render submitted.
pub(crate) async fn submitted(dir: &std::path::Path) -> (Arc<Engine>, i64) {
    submitted_as(CoreConfig::new(dir.to_path_buf()), request(&hash())).await
}

/// `req` rendered straight through on a fresh coordinator by one honest worker: the reference
/// a test's image (and adaptive budgets) must equal. Its directory goes with it.
pub(crate) async fn straight(req: Submission) -> (Arc<Engine>, i64, tempfile::TempDir) {
    let dir = fresh_dir("straight");
    let (engine, id) = submitted_as(CoreConfig::new(dir.path().to_path_buf()), req).await;
    work(&engine, &furnace(), usize::MAX).await;
    (engine, id, dir)
}

/// The test render with every pass fixed (no adaptive rounds).
pub(crate) fn fixed() -> Submission {
    Submission { adaptive: None, ..request(&hash()) }
}

/// A sequence of frames "1-3" of the test render, fixed 16 spp in passes of 4.
async fn sequence(engine: &Engine) -> i64 {
    let mut req = Submission { spp: 16, ..fixed() };
    req.frames = Some(Frames { list: FrameList::parse("1-3").unwrap(), fps: 24.0 });
    req.setup.pose = Some(Pose::default());
    match engine.submit(&crate::users::Identity::anyone(), req).await.unwrap() {
        Target::Sequence(id) => id,
        t => panic!("a sequence was submitted, {t} came back"),
    }
}

/// Runs `f` on the core.
pub(crate) fn on<T>(engine: &Engine, f: impl FnOnce(&mut Core) -> T) -> T {
    engine.with(|c| Ok(f(c))).unwrap()
}

pub(crate) fn state(engine: &Engine, id: i64) -> RenderState {
    on(engine, |c| c.status(id).unwrap().state)
}

/// A coordinator stopped after storing a render's last result but before writing its image
/// finishes it when it starts again (nothing is left to merge that would): the chaos test
/// once waited for ever on such a frame.
#[tokio::test]
async fn a_render_stored_whole_but_not_written_is_finished_at_start() {
    let dir = fresh_dir("stored-whole");
    let scene = furnace();
    let id = {
        let (engine, id) =
            submitted_as(CoreConfig::new(dir.path().to_path_buf()), Submission { spp: 16, ..fixed() }).await;
        let mut jobs = Vec::new();
        while let Some(job) = render_job(&engine, &scene).await {
            jobs.push(job);
        }
        let (last, rest) = jobs.split_last().unwrap();
        for (job, sums) in rest {
            complete(&engine, job, sums).await.unwrap();
        }
        // The last result is accepted and stored, and then the coordinator stops.
        let bytes = encode_tile_sums(&last.1);
        let lease = last.0.lease_id.to_string();
        let accepted = engine.with(|c| c.accept("w", &lease, Ok(last.1.clone()))).unwrap().unwrap();
        Store::reader(dir.path()).unwrap().apply(&accepted.stored(bytes)).unwrap();
        assert_eq!(state(&engine, id), RenderState::Running);
        id
    };
    let engine = open(dir.path());
    assert_eq!(state(&engine, id), RenderState::Done);
    assert!(on(&engine, |c| c.exr_path(id)).is_file(), "its image is written");
}

#[tokio::test]
async fn sequences_run_frames_in_order_keep_workers_on_their_frame_and_survive_a_restart() {
    let dir = fresh_dir("sequence");
    let scene = furnace();
    let lease = |engine: &Arc<Engine>, worker: &'static str| {
        let engine = engine.clone();
        async move { engine.lease(&Offer::plain(worker), None, Duration::ZERO).await.unwrap().unwrap() }
    };
    let seq = {
        let (engine, still) = submitted(dir.path()).await;
        engine.cancel(Target::Render(still)).await.unwrap();
        let seq = sequence(&engine).await;
        let s = on(&engine, |c| c.status_of(Target::Sequence(seq)).unwrap());
        assert_eq!((s.frames_total, s.frames_queued, s.frames_running), (3, 3, 0));
        assert_eq!(on(&engine, |c| c.film_bytes_held(None)), 0, "queued frames hold no film");
        // Each frame has its own seed and time; the first frame's id names the sequence.
        let frames = on(&engine, |c| c.members(Target::Sequence(seq)));
        assert_eq!(frames.len(), 3);
        let setup = |id: i64| on(&engine, |c| c.renders[&id].setup.clone());
        let pose = |id: i64| setup(id).pose.unwrap();
        assert_eq!((pose(frames[1]).frame, pose(frames[1]).time), (Some(2), 2.0 / 24.0));
        assert_ne!(setup(frames[0]).settings.seed, setup(frames[1]).settings.seed);
        // Worker a takes all of frame 1's passes (4 tiles x 4) before any of frame 2's.
        let mut a_jobs = Vec::new();
        let mut passes = 0;
        while passes < 16 {
            let job = lease(&engine, "a").await;
            assert_eq!(job.render_id, seq, "frame 1 first");
            passes += job.pass_count;
            a_jobs.push(job);
        }
        assert_eq!(lease(&engine, "a").await.render_id, frames[1]);
        // A job of frame 1 comes back: worker a stays on its frame 2, worker b takes frame 1's.
        engine.fail("a", &a_jobs[0].lease_id.to_string(), "out of memory").unwrap();
        assert_eq!(lease(&engine, "a").await.render_id, frames[1]);
        assert_eq!(lease(&engine, "b").await.render_id, seq);
        let s = on(&engine, |c| c.status_of(Target::Sequence(seq)).unwrap());
        assert_eq!((s.frames_running, s.frames_queued, s.frames_done), (0, 3, 0), "nothing merged yet");
        // The listing shows the sequence once.
        let (rows, _) = on(&engine, |c| c.list_renders(0, 100, |_| true));
        assert_eq!(rows.iter().map(|r| r.render_id.as_str()).collect::<Vec<_>>(), ["1", &format!("s{seq}")]);
        seq
    };
    // After a restart the leases are gone and the frames queued again; they finish, each
    // with its own image.
    let engine = open(dir.path());
    assert_eq!(on(&engine, |c| c.film_bytes_held(None)), 0);
    work(&engine, &scene, usize::MAX).await;
    let s = on(&engine, |c| c.status_of(Target::Sequence(seq)).unwrap());
    assert_eq!((s.state, s.frames_done), (RenderState::Done, 3));
    let (finished, all) = on(&engine, |c| c.finished_frames(seq, 0, 10));
    assert_eq!((finished.iter().map(|f| f.frame).collect::<Vec<_>>(), all), (vec![1, 2, 3], 3));
    let (rest, _) = on(&engine, |c| c.finished_frames(seq, 2, 10));
    assert_eq!(rest.iter().map(|f| f.frame).collect::<Vec<_>>(), [3], "told from where a watch got to");
    let second = engine.with(|c| c.frame_render(seq, 2)).unwrap();
    let header = String::from_utf8_lossy(&engine.image(second).await.unwrap()).into_owned();
    assert!(header.contains("frame=2") && header.contains("seed=3"), "the header names the frame");
    assert_eq!(on(&engine, |c| c.film_bytes_held(None)), 0, "finished frames drop their films");
    assert!(engine.with(|c| c.frame_render(seq, 9)).unwrap_err().to_string().contains("no frame 9"));
}

#[tokio::test]
async fn frames_that_cannot_resume_keep_their_frame_numbers() {
    let dir = fresh_dir("sequence-unresumable");
    let seq = {
        let (engine, still) = submitted(dir.path()).await;
        engine.cancel(Target::Render(still)).await.unwrap();
        sequence(&engine).await
    };
    // Today's limit is below the frames' plans: each frame fails to resume, saying why.
    let mut config = CoreConfig::new(dir.path().to_path_buf());
    config.max_passes = 1;
    let engine = Engine::open(config).unwrap();
    let s = on(&engine, |c| c.status_of(Target::Sequence(seq)).unwrap());
    assert_eq!((s.frames_failed, s.state), (3, RenderState::Failed));
    assert!(s.message.starts_with("frame 1: could not be resumed"), "{}", s.message);
    let second = engine.with(|c| c.frame_render(seq, 2)).unwrap();
    assert_eq!(on(&engine, |c| c.status(second).unwrap().frame), Some(2));
    assert!(engine.image(second).await.unwrap_err().to_string().contains("failed"));
}

/// A sequence's frames times its tiles are bounded before anything is stored (the frame list
/// and frame rate themselves are checked at the door: `tessera_request::wire`'s tests).
#[tokio::test]
async fn sequences_are_bounded_before_anything_is_stored() {
    let dir = fresh_dir("sequence-bounds");
    let (engine, still) = submitted(dir.path()).await;
    let metrics = |engine: &Engine| crate::http::metrics::prometheus(&on(engine, |c| c.farm_metrics()));
    let frames = |list: &str, fps| Some(Frames { list: FrameList::parse(list).unwrap(), fps });
    // 4 tiles a frame: 100,000 frames are 400,000 tiles, under the limit of 2^22.
    let mut req = request(&hash());
    req.frames = frames("0-99999", 1e6);
    let t = engine.submit(&crate::users::Identity::anyone(), req.clone()).await.unwrap();
    assert!(metrics(&engine).contains("tessera_pending_frames 100000"));
    engine.cancel(t).await.unwrap();
    let s = on(&engine, |c| c.status_of(t).unwrap());
    assert_eq!((s.state, s.frames_queued), (RenderState::Cancelled, 0));
    assert!(metrics(&engine).contains("tessera_pending_frames 0"));
    let next = engine.lease(&Offer::plain("w"), None, Duration::ZERO).await.unwrap();
    assert_eq!(next.map(|j| j.render_id), Some(still));
    engine.cancel(Target::Render(still)).await.unwrap();
    // 512 x 512 in 16-pixel tiles is 1024 tiles a frame: 4097 frames pass the limit.
    req.setup.settings = RenderSettings { width: 512, height: 512, ..settings() };
    req.frames = frames("0-4096", 24.0);
    let stored = Store::reader(dir.path()).unwrap().renders().unwrap().len();
    let e = engine.submit(&crate::users::Identity::anyone(), req).await.unwrap_err().to_string();
    assert!(e.contains("4097 frames of 1024 tiles"), "{e}");
    assert_eq!(Store::reader(dir.path()).unwrap().renders().unwrap().len(), stored, "nothing stored");
}

#[tokio::test]
async fn adaptive_rounds_replay_identically_after_a_restart() {
    let dir = fresh_dir("adaptive");
    let scene = furnace();
    let budget = |engine: &Engine, id: i64| on(engine, |c| c.renders[&id].budget.clone());
    let (id, budgets_before) = {
        let (engine, id) = submitted(dir.path()).await;
        work(&engine, &scene, 6).await;
        assert_eq!(state(&engine, id), RenderState::Running, "restart mid-render");
        (id, budget(&engine, id))
    };
    assert!(budgets_before.iter().any(|&b| b > 1), "some tile went past its first round: {budgets_before:?}");
    let engine = open(dir.path());
    assert_eq!(budget(&engine, id), budgets_before, "replayed rounds differ");
    work(&engine, &scene, usize::MAX).await;
    assert_eq!(state(&engine, id), RenderState::Done);
    // The same render straight through, without a restart, decides the same budgets and bits.
    let (straight, id2, _straight_dir) = straight(request(&hash())).await;
    assert_eq!(budget(&straight, id2), budget(&engine, id));
    assert_eq!(straight.image(id2).await.unwrap(), engine.image(id).await.unwrap(), "images differ");
}

/// The core holds no store: what it decides waits in `take_writes`, in the order decided,
/// until the engine commits it.
#[test]
fn the_core_writes_nothing_itself_and_its_writes_survive_a_restart() {
    let dir = fresh_dir("writes");
    let config = || CoreConfig::new(dir.path().to_path_buf());
    let store = Store::open(dir.path(), false).unwrap();
    let writes = {
        let mut core = Core::open(config(), &store).unwrap();
        let census = tessera_scene::Census { drawn_triangles: 100, cameras: 1, texels: 0, map_texels: 0 };
        let first = core.submit("", &request(&hash()), &census).unwrap().id();
        let second = core.submit("", &request(&hash()), &census).unwrap().id();
        core.cancel(first).unwrap();
        assert_eq!((first, second), (1, 2), "ids are the core's, given in order");
        assert!(store.renders().unwrap().is_empty(), "nothing written yet");
        core.take_writes()
    };
    let kinds: Vec<String> = writes.iter().map(|w| format!("{w:?}").split([' ', '(']).next().unwrap().into()).collect();
    let decided = ["CollectScenes", "Renders", "Log", "Renders", "Log", "Log", "State", "CollectScenes"];
    assert_eq!(kinds, decided, "in the order decided");
    for w in &writes {
        store.apply(w).unwrap();
    }
    let core = Core::open(config(), &store).unwrap();
    let states: Vec<RenderState> = [1, 2].map(|id| core.status(id).unwrap().state).to_vec();
    assert_eq!(states, [RenderState::Cancelled, RenderState::Running]);
    assert_eq!(core.next_id, 3, "ids go on after the stored ones");
    let log = store.log(crate::store::LogOf { id: 1, sequence: false }, 0, 10).unwrap().lines;
    let lines: Vec<&str> = log.iter().map(|l| l.line.as_str()).collect();
    assert!(lines[0].starts_with("submitted by anyone") && lines[1] == "cancelled", "{lines:?}");
}

#[tokio::test]
async fn finished_renders_reopen_without_their_film_and_images_survive() {
    let dir = fresh_dir("finished");
    let scene = furnace();
    let (id, image, status) = {
        let (engine, id) = submitted(dir.path()).await;
        work(&engine, &scene, usize::MAX).await;
        (id, engine.image(id).await.unwrap(), on(&engine, |c| c.status(id).unwrap()))
    };
    let engine = open(dir.path());
    assert_eq!(on(&engine, |c| c.renders[&id].film.width), 0, "no film is rebuilt for a finished render");
    let reopened = on(&engine, |c| c.status(id).unwrap());
    assert_eq!(
        (reopened.samples_done, reopened.passes_done, reopened.passes_total),
        (status.samples_done, status.passes_done, status.passes_total)
    );
    assert!(status.error_estimate > 0.0, "{status:?}");
    assert_eq!(reopened.error_estimate, status.error_estimate, "a finished render's error outlives a restart");
    assert_eq!(engine.image(id).await.unwrap(), image);
    std::fs::remove_file(dir.path().join("renders").join(format!("{id}.exr"))).unwrap();
    assert_eq!(engine.image(id).await.unwrap(), image, "a lost image is rebuilt from the stored results");
}

#[tokio::test]
async fn a_forged_sample_count_is_refused_and_the_lease_stays_live() {
    let dir = fresh_dir("forged");
    let scene = furnace();
    let (engine, id) = submitted(dir.path()).await;
    let (job, sums) = render_job(&engine, &scene).await.expect("a job");
    let mut forged = sums.clone();
    // n + dropped wraps a u64 to the expected count.
    let expected = forged.pixels[0].n;
    forged.pixels[0].n = u64::MAX;
    forged.pixels[0].dropped = expected + 1;
    let e = complete(&engine, &job, &forged).await.unwrap_err();
    assert!(matches!(e, EngineError::Core(CoreError::Invalid(_))), "{e}");
    assert_eq!(on(&engine, |c| c.status(id).unwrap().samples_done), 0, "nothing merged");
    assert_eq!(complete(&engine, &job, &sums).await.unwrap(), Outcome::Merged);
}

#[tokio::test]
async fn costly_renders_are_refused_before_anything_is_stored() {
    let dir = fresh_dir("costly");
    let engine = open(dir.path());
    engine.put_scene("", hash(), SCENE.to_vec()).await.unwrap();
    // 256 x 256 in 1 x 1 tiles of 1-sample passes at 4096 spp: 268 M passes.
    let mut req = fixed();
    req.setup.settings = RenderSettings { width: 256, height: 256, ..settings() };
    (req.tile_size, req.pass_spp, req.spp) = (1, 1, 4096);
    let e = engine.submit(&crate::users::Identity::anyone(), req).await.unwrap_err().to_string();
    assert!(e.contains("268435456 passes") && e.contains("over the limit"), "{e}");
    // Films: two 2048 x 2048 renders (512 MiB of sums each) fit under an 800 MiB limit one at a time, not together.
    drop(engine);
    let mut config = CoreConfig::new(dir.path().to_path_buf());
    config.max_film_bytes = 800 << 20;
    let engine = Engine::open(config).unwrap();
    let mut req = request(&hash());
    req.setup.settings = RenderSettings { width: 2048, height: 2048, ..settings() };
    let first = engine.submit(&crate::users::Identity::anyone(), req.clone()).await.unwrap();
    let e = engine.submit(&crate::users::Identity::anyone(), req).await.unwrap_err().to_string();
    assert!(e.contains("--max-film-bytes"), "{e}");
    engine.cancel(first).await.unwrap();
    assert_eq!(Store::reader(dir.path()).unwrap().renders().unwrap().len(), 1, "refused renders are not stored");
}

#[tokio::test]
async fn a_flipped_bit_in_a_stored_result_is_dropped_and_rendered_again() {
    let dir = fresh_dir("bitflip");
    let scene = furnace();
    let id = {
        let (engine, id) = submitted(dir.path()).await;
        work(&engine, &scene, 6).await;
        id
    };
    let db = rusqlite::Connection::open(dir.path().join("tessera.db")).unwrap();
    let (rowid, mut sums): (i64, Vec<u8>) = db
        .query_row("SELECT rowid, sums FROM results ORDER BY rowid LIMIT 1", [], |r| Ok((r.get(0)?, r.get(1)?)))
        .unwrap();
    let last = sums.len() - 1;
    sums[last] ^= 0x01; // still decodes, to a different sum
    db.execute("UPDATE results SET sums = ?1 WHERE rowid = ?2", rusqlite::params![sums, rowid]).unwrap();
    drop(db);
    let engine = open(dir.path());
    work(&engine, &scene, usize::MAX).await;
    assert_eq!(state(&engine, id), RenderState::Done);
    let (straight, id2, _straight_dir) = straight(request(&hash())).await;
    assert_eq!(straight.image(id2).await.unwrap(), engine.image(id).await.unwrap(), "the corrupt result was merged");
}

/// A flipped bit in a stored scene is caught where the scene is read: the copy is deleted (so
/// the next submit uploads it again), its renders fail saying why, and once it is uploaded again
/// a retry finishes them with the bits of a render that never met the damage.
#[tokio::test]
async fn a_flipped_bit_in_a_stored_scene_is_caught_reuploaded_and_retried() {
    let dir = fresh_dir("scene-bitflip");
    let scene = furnace();
    let (engine, id) = submitted(dir.path()).await;
    work(&engine, &scene, 3).await;
    let db = rusqlite::Connection::open(dir.path().join("tessera.db")).unwrap();
    let mut bytes: Vec<u8> = db.query_row("SELECT bytes FROM scenes", [], |r| r.get(0)).unwrap();
    bytes[10] ^= 0x01;
    db.execute("UPDATE scenes SET bytes = ?1", [bytes]).unwrap();
    drop(db);
    // A worker asks for it: refused, the copy deleted, the render failed saying why.
    let e = engine.scene_bytes(&hash()).await.unwrap_err().to_string();
    assert!(e.contains("corrupt") && e.contains("submit the scene again"), "{e}");
    let status = on(&engine, |c| c.status(id).unwrap());
    assert_eq!(status.state, RenderState::Failed);
    assert!(status.message.contains("its scene is lost"), "{}", status.message);
    assert!(
        !engine.has_scene(&crate::users::Identity::anyone(), &hash()).await.unwrap(),
        "a client is told to upload it again"
    );
    // Uploaded again and retried, it finishes with the bits of an undamaged render.
    engine.put_scene("", hash(), SCENE.to_vec()).await.unwrap();
    assert!(engine.has_scene(&crate::users::Identity::anyone(), &hash()).await.unwrap());
    engine.retry(Target::Render(id)).await.unwrap();
    work(&engine, &scene, usize::MAX).await;
    assert_eq!(state(&engine, id), RenderState::Done);
    let (straight, id2, _straight_dir) = straight(request(&hash())).await;
    assert_eq!(straight.image(id2).await.unwrap(), engine.image(id).await.unwrap(), "images differ");
}

/// `has_scene` checks the bytes too: a corrupted copy is not reused by the next submit.
#[tokio::test]
async fn a_corrupted_scene_is_not_reused_by_a_later_submit() {
    let dir = fresh_dir("scene-reuse");
    let engine = open(dir.path());
    engine.put_scene("", hash(), SCENE.to_vec()).await.unwrap();
    drop(engine);
    let db = rusqlite::Connection::open(dir.path().join("tessera.db")).unwrap();
    db.execute("UPDATE scenes SET bytes = ?1", [b"tessera-builtin:furnace?base=0.9".to_vec()]).unwrap();
    drop(db);
    let engine = open(dir.path());
    assert!(!engine.has_scene(&crate::users::Identity::anyone(), &hash()).await.unwrap());
    let e = engine.submit(&crate::users::Identity::anyone(), request(&hash())).await.unwrap_err().to_string();
    assert!(e.contains("upload it") || e.contains("submit the scene again"), "the corrupt copy is not used: {e}");
    engine.put_scene("", hash(), SCENE.to_vec()).await.unwrap();
    assert!(
        engine.submit(&crate::users::Identity::anyone(), request(&hash())).await.is_ok(),
        "uploaded again, it renders"
    );
}

/// A GLB of one mesh of `triangles` triangles drawn by `instances` nodes.
fn instanced_glb(triangles: usize, instances: usize) -> Vec<u8> {
    let positions: Vec<f32> = (0..triangles)
        .flat_map(|i| {
            let x = i as f32 * 0.01;
            [x, 0.0, 0.0, x + 0.01, 0.0, 0.0, x, 0.01, 0.0]
        })
        .collect();
    let bin: Vec<u8> = positions.iter().flat_map(|v| v.to_le_bytes()).collect();
    let nodes: Vec<String> =
        (0..instances).map(|i| format!(r#"{{"mesh":0,"translation":[0,0,{}]}}"#, i as f32 * 0.1)).collect();
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},"scenes":[{{"nodes":[{}]}}],"nodes":[{}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":{},"type":"VEC3","min":[0,0,0],"max":[{},0.01,0]}}],
        "bufferViews":[{{"buffer":0,"byteLength":{}}}],"buffers":[{{"byteLength":{}}}]}}"#,
        (0..instances).map(|i| i.to_string()).collect::<Vec<_>>().join(","),
        nodes.join(","),
        3 * triangles,
        triangles as f32 * 0.01 + 0.01,
        bin.len(),
        bin.len()
    );
    let mut json = json.into_bytes();
    json.resize(json.len().next_multiple_of(4), b' ');
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let mut glb = Vec::new();
    for word in [0x4654_6c67u32, 2, total as u32, json.len() as u32, 0x4e4f_534a] {
        glb.extend(word.to_le_bytes());
    }
    glb.extend(&json);
    for word in [bin.len() as u32, 0x004e_4942] {
        glb.extend(word.to_le_bytes());
    }
    glb.extend(&bin);
    glb
}

/// What a render of a scene costs is counted before anything is built, however the file
/// instances its meshes: accepting the upload and the submit builds nothing, and a scene whose
/// drawn triangles would take a worker more than --max-scene-memory is refused saying so; under
/// a budget that holds it, it renders.
#[tokio::test]
async fn instanced_scenes_are_counted_not_built_and_held_to_a_memory_budget() {
    let dir = fresh_dir("instancing");
    let glb = instanced_glb(1000, 50);
    let hash = blake3::hash(&glb).to_hex().to_string();
    let mut config = CoreConfig::new(dir.path().to_path_buf());
    config.max_scene_memory = 10 << 20;
    let engine = Engine::open(config).unwrap();
    engine.put_scene("", hash.clone(), glb.clone()).await.unwrap();
    let mut req = Submission { scene_hash: hash.clone(), scene_name: "instanced".into(), ..fixed() };
    req.setup.settings.camera = 0;
    let e = engine.submit(&crate::users::Identity::anyone(), req.clone()).await.unwrap_err().to_string();
    assert!(e.contains("50000 triangles drawn") && e.contains("--max-scene-memory"), "{e}");
    // 50,000 triangles at 400 bytes is 19 MiB: under a 32 MiB budget it is accepted and renders.
    drop(engine);
    let mut config = CoreConfig::new(dir.path().to_path_buf());
    config.max_scene_memory = 32 << 20;
    let engine = Engine::open(config).unwrap();
    let id = engine.submit(&crate::users::Identity::anyone(), req).await.unwrap().id();
    let scene = tessera_scene::load_packed(&glb, "instanced", &Default::default()).unwrap();
    assert_eq!(scene.info.triangles, 50_000, "the census counted what a build draws");
    assert_eq!(state(&engine, id), RenderState::Running);
    // The core refuses what the census counts over --max-triangles, whatever the budget.
    let census = tessera_scene::Census { drawn_triangles: 30_000_000, cameras: 1, texels: 0, map_texels: 0 };
    let e = engine.with(|c| c.submit("", &fixed(), &census)).unwrap_err().to_string();
    assert!(e.contains("draws 30000000 triangles") && e.contains("--max-triangles"), "{e}");
}

#[tokio::test]
async fn a_render_that_cannot_resume_fails_and_the_rest_resume() {
    let dir = fresh_dir("unresumable");
    let (broken, wide, fine) = {
        let (engine, broken) = submitted(dir.path()).await;
        let anyone = crate::users::Identity::anyone();
        let submit = || engine.submit(&anyone, request(&hash()));
        (broken, submit().await.unwrap().id(), submit().await.unwrap().id())
    };
    let db = rusqlite::Connection::open(dir.path().join("tessera.db")).unwrap();
    db.execute("UPDATE renders SET settings = x'ff' WHERE id = ?1", [broken]).unwrap();
    // Stored before results were bounded: its tiles could make results no coordinator accepts.
    db.execute("UPDATE renders SET tile_size = 1024 WHERE id = ?1", [wide]).unwrap();
    drop(db);
    for _ in 0..2 {
        let engine = open(dir.path());
        for (id, why) in [(broken, "could not be resumed"), (wide, "use tiles of at most")] {
            let status = on(&engine, |c| c.status(id).unwrap());
            assert_eq!(status.state, RenderState::Failed);
            assert!(status.message.contains(why), "{}", status.message);
        }
        assert_eq!(state(&engine, fine), RenderState::Running);
    }
}

#[tokio::test]
async fn an_empty_database_beside_render_images_is_refused() {
    let dir = fresh_dir("emptydb");
    let scene = furnace();
    {
        let (engine, _) = submitted(dir.path()).await;
        work(&engine, &scene, usize::MAX).await;
    }
    for f in ["tessera.db-wal", "tessera.db-shm"] {
        let _ = std::fs::remove_file(dir.path().join(f));
    }
    let reopened = || Engine::open(CoreConfig::new(dir.path().to_path_buf())).err().expect("refused").to_string();
    std::fs::write(dir.path().join("tessera.db"), b"").unwrap();
    let e = reopened();
    assert!(e.contains("is empty (0 bytes)") && e.contains("Restore it from a backup"), "{e}");
    std::fs::write(dir.path().join("tessera.db"), b"not a database, just junk bytes of some length").unwrap();
    let e = reopened();
    assert!(e.contains("not a readable SQLite database"), "{e}");
}

/// Before any render has finished (no image written), a lost or truncated database is still
/// refused: the marker its schema left says one was there, and so does a write-ahead log it left.
/// A fresh directory starts empty.
#[tokio::test]
async fn a_lost_database_is_refused_before_any_render_finished() {
    let dir = fresh_dir("lostdb");
    let scene = furnace();
    {
        let (engine, _) = submitted(dir.path()).await;
        work(&engine, &scene, 3).await;
    }
    assert_eq!(std::fs::read_dir(dir.path().join("renders")).unwrap().count(), 0, "no image yet");
    let reopened = || Engine::open(CoreConfig::new(dir.path().to_path_buf())).err().expect("refused").to_string();
    for f in ["tessera.db", "tessera.db-wal", "tessera.db-shm"] {
        let _ = std::fs::remove_file(dir.path().join(f));
    }
    let e = reopened();
    assert!(e.contains("is missing") && e.contains(crate::store::CREATED), "{e}");
    std::fs::write(dir.path().join("tessera.db"), b"").unwrap();
    assert!(reopened().contains("is empty (0 bytes)"));
    // Without the marker, the log a killed coordinator left says it.
    std::fs::remove_file(dir.path().join(crate::store::CREATED)).unwrap();
    std::fs::write(dir.path().join("tessera.db-wal"), vec![7u8; 4096]).unwrap();
    let e = reopened();
    assert!(e.contains("write-ahead log") && e.contains("4096 bytes"), "{e}");
    // Nothing at all: a new farm.
    std::fs::remove_file(dir.path().join("tessera.db-wal")).unwrap();
    std::fs::remove_file(dir.path().join("tessera.db")).unwrap();
    assert!(Engine::open(CoreConfig::new(dir.path().to_path_buf())).is_ok());
    assert!(dir.path().join(crate::store::CREATED).exists(), "the new database leaves its marker");
}

/// The stored result ranges of render `id` in the database in `dir`.
fn stored_ranges(dir: &std::path::Path, id: i64) -> usize {
    Store::reader(dir).unwrap().ranges(id).map_or(0, |r| r.len())
}

/// A graceful stop checkpoints: the write-ahead log is emptied into `tessera.db`, so that a copy
/// of that file alone (what an operator backs up) holds every result. Before, the data stayed
/// in the log and such a copy lost everything since SQLite's last automatic checkpoint.
#[tokio::test]
async fn a_checkpoint_leaves_everything_in_the_database_file() {
    let (dir, copy) = (fresh_dir("checkpoint"), fresh_dir("checkpoint-copy"));
    let scene = furnace();
    let (engine, id) = submitted(dir.path()).await;
    work(&engine, &scene, 3).await;
    engine.checkpoint().await.unwrap();
    assert_eq!(std::fs::metadata(dir.path().join("tessera.db-wal")).map_or(0, |m| m.len()), 0, "the log is empty");
    // The process ends here without unwinding; an operator copies tessera.db (and its marker).
    for f in ["tessera.db", crate::store::CREATED] {
        std::fs::copy(dir.path().join(f), copy.path().join(f)).unwrap();
    }
    let restored = open(copy.path());
    assert_eq!(state(&restored, id), RenderState::Running);
    assert_eq!(stored_ranges(copy.path(), id), 3, "every result is in the copied file");
    drop(engine);
}

/// `tessera backup` while the coordinator serves: the copy is one consistent snapshot, and a
/// coordinator started on it resumes the render and finishes it to the same bits as the
/// original did.
#[tokio::test]
async fn a_backup_taken_while_serving_restores_to_the_same_image() {
    let (dir, backup) = (fresh_dir("backup"), fresh_dir("backup-copy"));
    let scene = furnace();
    let (engine, id) = submitted(dir.path()).await;
    work(&engine, &scene, 4).await;
    let copied = crate::store::backup(dir.path(), backup.path()).unwrap();
    assert_eq!((copied.renders, copied.results, copied.scenes), (1, 4, 1));
    let again = crate::store::backup(dir.path(), backup.path()).unwrap_err().to_string();
    assert!(again.contains("already exists"), "{again}");
    work(&engine, &scene, usize::MAX).await;
    assert_eq!(state(&engine, id), RenderState::Done);

    let restored = open(backup.path());
    assert_eq!(stored_ranges(backup.path(), id), 4, "the snapshot's results, no more");
    assert_eq!(state(&restored, id), RenderState::Running);
    work(&restored, &scene, usize::MAX).await;
    assert_eq!(state(&restored, id), RenderState::Done);
    assert_eq!(restored.image(id).await.unwrap(), engine.image(id).await.unwrap(), "images differ");
    let missing = crate::store::backup(&dir.path().join("nothing"), &backup.path().join("x")).unwrap_err();
    assert!(missing.to_string().contains("--data-dir"), "{missing}");
}

#[tokio::test]
async fn worker_names_are_bounded_and_listings_come_in_pages() {
    let dir = fresh_dir("names");
    let (engine, _) = submitted(dir.path()).await;
    let long = "w".repeat(2000);
    assert!(engine.lease(&Offer { name: "w".into(), ..Offer::plain(&long) }, None, Duration::ZERO).await.is_err());
    assert!(
        engine.lease(&Offer { name: "evil\x1b[2J".into(), ..Offer::plain("w") }, None, Duration::ZERO).await.is_err()
    );
    for _ in 0..4 {
        engine.submit(&crate::users::Identity::anyone(), request(&hash())).await.unwrap();
    }
    let (page, more) = on(&engine, |c| c.list_renders(0, 2, |_| true));
    assert_eq!((page.iter().map(|r| r.render_id.as_str()).collect::<Vec<_>>(), more), (vec!["1", "2"], true));
    let (page, more) = on(&engine, |c| c.list_renders(4, 2, |_| true));
    assert_eq!((page.len(), more), (1, false));
}

#[tokio::test]
async fn ignored_results_are_counted_by_reason() {
    let dir = fresh_dir("ignored");
    let scene = furnace();
    let (engine, _) = submitted(dir.path()).await;
    let (job, sums) = render_job(&engine, &scene).await.expect("a job");
    let bytes = encode_tile_sums(&sums);
    assert_eq!(complete(&engine, &job, &sums).await.unwrap(), Outcome::Merged);
    assert_eq!(complete(&engine, &job, &sums).await.unwrap(), Outcome::Ignored(Ignored::Duplicate));
    for lease in ["12345", "not-a-lease"] {
        assert_eq!(engine.complete("w", lease, bytes.clone()).await.unwrap(), Outcome::Ignored(Ignored::Unknown));
    }
    let text = crate::http::metrics::prometheus(&on(&engine, |c| c.farm_metrics()));
    assert!(text.contains("tessera_results_ignored_total{reason=\"duplicate\"} 1\n"), "{text}");
    assert!(text.contains("tessera_results_ignored_total{reason=\"unknown_lease\"} 2\n"), "{text}");
    assert!(text.contains("tessera_results_ignored_total{reason=\"late\"} 0\n"), "{text}");
}

#[tokio::test]
async fn failed_jobs_block_their_worker_then_fail_the_render_and_retry_finishes_it() {
    let dir = fresh_dir("failures");
    let mut config = CoreConfig::new(dir.path().to_path_buf());
    (config.max_attempts, config.block_after) = (3, 2);
    let (engine, id) = submitted_as(config, fixed()).await;
    let (bad, bad2, good) = (Offer::plain("bad"), Offer::plain("bad2"), Offer::plain("good"));
    let lease = |offer| engine.lease(offer, None, Duration::ZERO);
    for _ in 0..2 {
        let job = lease(&bad).await.unwrap().expect("a job");
        engine.fail("bad", &job.lease_id.to_string(), "out of memory").unwrap();
    }
    assert!(lease(&bad).await.unwrap().is_none(), "a worker that failed twice is blocked");
    let status = on(&engine, |c| c.status(id).unwrap());
    assert_eq!(status.state, RenderState::Running);
    assert!(status.message.contains("out of memory"), "{}", status.message);
    // The same passes come back first; their third failure fails the render.
    let job = lease(&bad2).await.unwrap().expect("another worker gets the job");
    assert_eq!(job.first_pass, 0);
    engine.fail("bad2", &job.lease_id.to_string(), "scene did not load").unwrap();
    let status = on(&engine, |c| c.status(id).unwrap());
    assert_eq!(status.state, RenderState::Failed);
    assert!(
        status.message.contains("failed 3 times") && status.message.contains("scene did not load"),
        "{}",
        status.message
    );
    assert!(lease(&good).await.unwrap().is_none(), "a failed render hands out nothing");
    assert!(matches!(engine.image(id).await, Err(EngineError::Core(CoreError::NotReady(_)))));
    // Retried, it finishes with the same bits as a render that never failed.
    engine.retry(Target::Render(id)).await.unwrap();
    assert!(engine.retry(Target::Render(id)).await.is_err(), "a running render is not retried");
    let scene = furnace();
    work(&engine, &scene, usize::MAX).await;
    assert_eq!(state(&engine, id), RenderState::Done);
    let (straight, id2, _straight_dir) = straight(fixed()).await;
    assert_eq!(straight.image(id2).await.unwrap(), engine.image(id).await.unwrap(), "images differ");
}

#[tokio::test]
async fn expired_leases_count_as_attempts_and_failures_survive_a_restart() {
    let dir = fresh_dir("expiries");
    let mut config = CoreConfig::new(dir.path().to_path_buf());
    (config.max_attempts, config.lease_ms) = (2, 1);
    let (engine, id) = submitted_as(config, fixed()).await;
    for _ in 0..3 {
        let _ = engine.lease(&Offer::plain("w"), None, Duration::ZERO).await.unwrap();
        std::thread::sleep(Duration::from_millis(5));
    }
    let status = on(&engine, |c| c.status(id).unwrap());
    assert_eq!(status.state, RenderState::Failed);
    assert!(status.message.contains("lease expired"), "{}", status.message);
    drop(engine);
    let engine = open(dir.path());
    let status = on(&engine, |c| c.status(id).unwrap());
    assert_eq!(status.state, RenderState::Failed, "still failed after a restart");
    assert!(status.message.contains("lease expired"), "{}", status.message);
    engine.retry(Target::Render(id)).await.unwrap();
    assert_eq!(state(&engine, id), RenderState::Running);
}

/// Results committed outside the lock merge in whatever order their commits finish. Leased
/// in batches of five, accepted together and committed and merged in reverse, an adaptive
/// render decides the same rounds and ends with the same image as one merged as it goes: a
/// tile's next round is decided only once the film holds all of its current one.
#[tokio::test]
async fn results_merged_out_of_order_give_the_same_rounds_and_film() {
    let scene = furnace();
    let dir = fresh_dir("reordered");
    let (engine, id) = submitted(dir.path()).await;
    loop {
        let mut batch = Vec::new();
        while batch.len() < 5 {
            let Some((job, sums)) = render_job(&engine, &scene).await else { break };
            let lease = job.lease_id.to_string();
            let accepted = engine.with(|c| c.accept("w", &lease, Ok(sums.clone()))).unwrap().unwrap();
            batch.push((accepted, encode_tile_sums(&sums)));
        }
        if batch.is_empty() {
            break;
        }
        for (accepted, bytes) in batch.into_iter().rev() {
            engine.commit_and_merge(accepted, bytes).await.unwrap();
        }
    }
    assert_eq!(state(&engine, id), RenderState::Done);
    let budget = |engine: &Engine, id: i64| on(engine, |c| c.renders[&id].budget.clone());
    let (straight, id2, _straight_dir) = straight(request(&hash())).await;
    assert_eq!(budget(&straight, id2), budget(&engine, id), "rounds differ");
    assert_eq!(straight.image(id2).await.unwrap(), engine.image(id).await.unwrap(), "images differ");
    assert!(budget(&engine, id).iter().any(|&b| b > 1), "no tile went past its first round");
}

#[tokio::test]
async fn scenes_no_render_needs_are_collected_after_a_grace_period() {
    let dir = fresh_dir("scene-gc");
    let scene = furnace();
    let (engine, done) = submitted(dir.path()).await;
    let other = b"tessera-builtin:cornell-box".to_vec();
    let other_hash = blake3::hash(&other).to_hex().to_string();
    engine.put_scene("", other_hash.clone(), other).await.unwrap();
    work(&engine, &scene, usize::MAX).await;
    assert_eq!(state(&engine, done), RenderState::Done);
    let collect = || {
        engine.with_durable(|c| {
            c.collect_scenes();
            Ok(())
        })
    };
    let stored = |hash: &str| Store::reader(dir.path()).unwrap().has_scene(hash).unwrap();
    // Both scenes are within their grace period: kept.
    collect().await.unwrap();
    assert!(stored(&other_hash));
    // An hour later the unused upload and the finished render's scene go; a running render's
    // scene stays however old.
    let running = engine.submit(&crate::users::Identity::anyone(), request(&hash())).await.unwrap();
    let db = rusqlite::Connection::open(dir.path().join("tessera.db")).unwrap();
    db.execute("UPDATE scenes SET stored_at = stored_at - 7200", []).unwrap();
    collect().await.unwrap();
    assert!(!stored(&other_hash), "an unused scene was kept");
    assert!(stored(&hash()), "a running render's scene was deleted");
    engine.cancel(running).await.unwrap();
    assert!(!stored(&hash()), "a cancelled render keeps its scene");
}

/// With per-user tokens, a submitter neither learns whether another user's scene is stored nor
/// renders it by its hash alone: both are answered as for a missing scene, and uploading it
/// (the client's answer to that) makes it theirs. An admin uses any. `tessera workers` shows a
/// submitter the renders of their own jobs only.
#[tokio::test]
async fn a_submitter_neither_sees_nor_uses_another_users_scene_or_render_ids() {
    use crate::users::{Identity, Role};
    let dir = fresh_dir("scene-owners");
    let engine = open(dir.path());
    let user = |name: &str| Identity { name: name.into(), role: Role::Submit };
    let (alice, bob, root) = (user("alice"), user("bob"), Identity { name: "root".into(), role: Role::Admin });
    engine.put_scene("alice", hash(), SCENE.to_vec()).await.unwrap();
    assert!(engine.has_scene(&alice, &hash()).await.unwrap());
    assert!(!engine.has_scene(&bob, &hash()).await.unwrap(), "bob learns alice's scene is stored");
    let e = engine.submit(&bob, fixed()).await.unwrap_err().to_string();
    assert!(e.contains("upload it first"), "{e}");
    assert!(engine.has_scene(&root, &hash()).await.unwrap());
    let alices = engine.submit(&alice, fixed()).await.unwrap().id();
    engine.put_scene("bob", hash(), SCENE.to_vec()).await.unwrap();
    assert!(engine.has_scene(&bob, &hash()).await.unwrap(), "uploaded, it is bob's too");
    engine.submit(&bob, fixed()).await.unwrap();
    // A worker holds a job of alice's render: only alice and the admin see which.
    let job = engine.lease(&Offer::plain("w"), None, Duration::ZERO).await.unwrap().unwrap();
    assert_eq!(job.render_id, alices);
    let renders = |who: &Identity| on(&engine, |c| c.list_workers_for(who, "", 10).0[0].renders.clone());
    assert_eq!(renders(&alice), vec![alices]);
    assert_eq!(renders(&root), vec![alices]);
    assert!(renders(&bob).is_empty(), "bob sees alice's render id");
}
