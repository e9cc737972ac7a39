//! The farm's bookkeeping: workers and their states, frames waiting over the farm, cancelled
//! renders resumed, and the data directory one coordinator holds.

use super::*;

/// Frames waiting or rendering are bounded over the farm (each holds memory until it
/// finishes): a sequence that would pass the limit is refused, saying so, until others end.
#[tokio::test]
async fn queued_frames_are_bounded_over_the_farm() {
    let dir = fresh_dir("queued-frames");
    let config = CoreConfig { max_queued_frames: 5, ..CoreConfig::new(dir.path().to_path_buf()) };
    let (engine, _) = submitted_as(config, Submission { spp: 16, ..fixed() }).await;
    let who = crate::users::Identity::anyone();
    let frames = |list: &str| Some(Frames { list: FrameList::parse(list).unwrap(), fps: 24.0 });
    let first = engine.submit(&who, Submission { frames: frames("1-3"), ..fixed() }).await.unwrap();
    let e = engine.submit(&who, Submission { frames: frames("1-3"), ..fixed() }).await.unwrap_err().to_string();
    assert!(e.contains("limit of 5 frames waiting or rendering") && e.contains("3 are now"), "{e}");
    engine.cancel(first).await.unwrap();
    engine.submit(&who, Submission { frames: frames("1-5"), ..fixed() }).await.unwrap();
}

/// Workers show what they are doing: busy, idle, stopped (they said goodbye), lost (not heard
/// from for two lease times, their leases expired and counted as their failures), and the
/// renders they get no more jobs of.
#[tokio::test]
async fn workers_show_their_states_and_an_expired_lease_counts_as_a_failure() {
    use crate::model::WorkerState;
    let dir = fresh_dir("worker-states");
    // d fails the same pass three times (a failed pass is first in line again): not the render.
    let config = CoreConfig { lease_ms: 400, max_attempts: 10, ..CoreConfig::new(dir.path().to_path_buf()) };
    let (engine, id) = submitted_as(config, fixed()).await;
    let scene = furnace();
    let lease = async |w: &str| engine.lease(&Offer::plain(w), None, Duration::ZERO).await.unwrap().unwrap();
    lease("a").await;
    let job = lease("b").await;
    let samples = RenderPlan::new(64, 16, 16, job.spp, job.pass_spp).samples(job.first_pass, job.pass_count);
    let sums = render_tile(&scene, &job.setup.settings, job.tile, samples).unwrap();
    engine.complete("b", &job.lease_id.to_string(), encode_tile_sums(&sums)).await.unwrap();
    let job = lease("c").await;
    engine.release("c", &[job.lease_id.to_string()]).unwrap();
    for _ in 0..3 {
        let job = lease("d").await;
        engine.fail("d", &job.lease_id.to_string(), "out of memory").unwrap();
    }
    let states = || {
        on(&engine, |c| {
            c.list_workers("", 10).0.into_iter().map(|w| (w.worker_id, (w.state, w.failures, w.blocked_from))).collect()
        })
    };
    let now: HashMap<String, (WorkerState, u64, Vec<i64>)> = states();
    assert_eq!(now["a"], (WorkerState::Busy, 0, vec![]));
    assert_eq!(now["b"], (WorkerState::Idle, 0, vec![]));
    assert_eq!(now["c"], (WorkerState::Stopped, 0, vec![]));
    assert_eq!(now["d"], (WorkerState::Idle, 3, vec![id]));
    // "a" falls silent past two lease times; "b" keeps asking.
    tokio::time::sleep(Duration::from_millis(900)).await;
    on(&engine, |c| c.heartbeat("b", &[]));
    let later = states();
    assert_eq!(later["a"], (WorkerState::Lost, 1, vec![]), "its expired lease is its failure");
    assert_eq!(later["b"].0, WorkerState::Idle);
}

/// A second coordinator on the same data directory is refused, naming the first's pid; once
/// the first has stopped, the directory is free.
#[test]
fn a_data_directory_serves_one_coordinator_at_a_time() {
    let dir = fresh_dir("lock");
    let first = open(dir.path());
    let e = Engine::open(CoreConfig::new(dir.path().to_path_buf())).err().expect("a second coordinator");
    let message = e.to_string();
    assert!(message.contains(&format!("process {} holds", std::process::id())), "{message}");
    assert!(message.contains("another --data-dir"), "{message}");
    drop(first);
    open(dir.path());
}

/// A cancelled render says so when its image is asked for, and `retry` resumes it keeping what
/// it merged: the image is the one a render straight through gives.
#[tokio::test]
async fn a_cancelled_render_says_so_and_resumes_where_it_stopped() {
    let dir = fresh_dir("cancel-resume");
    let scene = furnace();
    let (engine, id) = submitted_as(CoreConfig::new(dir.path().to_path_buf()), fixed()).await;
    work(&engine, &scene, 5).await;
    engine.cancel(Target::Render(id)).await.unwrap();
    let e = engine.image(id).await.unwrap_err().to_string();
    assert!(e.contains("was cancelled") && e.contains(&format!("tessera retry {id}")), "{e}");
    let merged = on(&engine, |c| c.status(id).unwrap().passes_done);
    assert!(merged > 0);
    engine.retry(Target::Render(id)).await.unwrap();
    assert_eq!(on(&engine, |c| c.status(id).unwrap().passes_done), merged, "what it merged is kept");
    work(&engine, &scene, usize::MAX).await;
    assert_eq!(state(&engine, id), RenderState::Done);
    let (straight, id2, _straight_dir) = straight(fixed()).await;
    assert_eq!(straight.image(id2).await.unwrap(), engine.image(id).await.unwrap(), "images differ");
}

/// A render's bookkeeping is stored and survives a restart: when it was submitted, started (its
/// first job) and ended, its run time counted from its start (not its time in the queue) and
/// frozen at its end, and its speed over the time it ran.
#[tokio::test]
async fn submitted_started_and_ended_survive_a_restart() {
    let dir = fresh_dir("bookkeeping");
    let scene = furnace();
    let (id, before) = {
        let (engine, id) = submitted_as(CoreConfig::new(dir.path().to_path_buf()), fixed()).await;
        let queued = on(&engine, |c| c.status(id).unwrap());
        assert!(queued.submitted_at.is_some() && queued.started_at.is_none(), "{queued:?}");
        assert_eq!(on(&engine, |c| c.elapsed(Target::Render(id))), Some(0.0), "time in the queue is not run time");
        tokio::time::sleep(Duration::from_millis(300)).await;
        work(&engine, &scene, usize::MAX).await;
        (id, on(&engine, |c| (c.status(id).unwrap(), c.elapsed(Target::Render(id)).unwrap())))
    };
    let (status, ran) = before;
    let (submitted, started, ended) =
        (status.submitted_at.unwrap(), status.started_at.unwrap(), status.ended_at.unwrap());
    assert!(submitted + 0.25 <= started && started <= ended, "{status:?}");
    assert!((ran - (ended - started)).abs() < 1e-6);
    tokio::time::sleep(Duration::from_millis(300)).await;
    let engine = open(dir.path());
    let after = on(&engine, |c| c.status(id).unwrap());
    assert_eq!((after.submitted_at, after.started_at), (status.submitted_at, status.started_at));
    assert_eq!(after.ended_at, status.ended_at);
    let ran_after = on(&engine, |c| c.elapsed(Target::Render(id)).unwrap());
    assert_eq!(ran_after, ran, "the run time read back");
    assert_eq!(after.samples_per_second, status.samples_per_second, "the speed read back");
}

/// A render with the feature layers (`--aov`) takes only results that carry them, and a render
/// without them only results that do not: checked before anything is stored, the lease kept. Its
/// image then has the layers, also when rebuilt from the stored results (its file gone).
#[tokio::test]
async fn feature_layers_are_there_exactly_when_the_render_asked_for_them() {
    let scene = furnace();
    for asked in [true, false] {
        let dir = fresh_dir("features");
        let mut req = fixed();
        req.setup.settings.features = asked;
        let (engine, id) = submitted_as(CoreConfig::new(dir.path().to_path_buf()), req).await;
        let (job, sums) = render_job(&engine, &scene).await.expect("a job");
        assert_eq!(sums.features.is_empty(), !asked, "the worker renders what the render asked for");
        let mut wrong = sums.clone();
        wrong.features = if asked { Vec::new() } else { vec![Default::default(); sums.pixels.len()] };
        let e = complete(&engine, &job, &wrong).await.unwrap_err().to_string();
        assert!(e.contains("feature layers"), "{e}");
        assert_eq!(on(&engine, |c| c.status(id).unwrap().samples_done), 0, "nothing merged");
        assert_eq!(complete(&engine, &job, &sums).await.unwrap(), Outcome::Merged);
        work(&engine, &scene, usize::MAX).await;
        let written = tessera_film::read_exr_bytes(&engine.image(id).await.unwrap(), "image").unwrap();
        assert_eq!(written.features.is_some(), asked);
        let exr = on(&engine, |c| c.image_path(id).unwrap().0);
        std::fs::remove_file(exr).unwrap();
        let rebuilt = tessera_film::read_exr_bytes(&engine.image(id).await.unwrap(), "image").unwrap();
        assert_eq!(rebuilt, written, "rebuilt from the stored results, layers and all");
    }
}

/// A stand-in denoiser: each pixel the mean of its colour's channels; or one that fails.
struct Grey {
    fails: bool,
}

impl tessera_film::Denoiser for Grey {
    fn name(&self) -> String {
        "grey 1.0".into()
    }
    fn denoise(&self, _: u32, _: u32, c: &[[f32; 3]], _: &[[f32; 3]], _: &[[f32; 3]]) -> Result<Vec<[f32; 3]>, String> {
        if self.fails {
            return Err("out of memory".into());
        }
        Ok(c.iter().map(|p| [(p[0] + p[1] + p[2]) / 3.0; 3]).collect())
    }
}

/// `--denoise` on the farm: a coordinator without a denoiser refuses the render before storing
/// anything; one with a denoiser writes the `denoised` layer beside raw channels equal to an
/// undenoised render's, names the denoiser in the header, and denoises again when the image is
/// rebuilt from the store; a denoiser that fails leaves the raw image, its header saying why.
#[tokio::test]
async fn a_denoised_render_adds_its_layer_and_keeps_the_raw_colour() {
    let scene = furnace();
    let mut req = fixed();
    (req.setup.settings.features, req.setup.settings.denoise) = (true, true);
    let dir = fresh_dir("denoise-refused");
    let engine = Engine::open(CoreConfig::new(dir.path().to_path_buf())).unwrap();
    engine.put_scene("", hash(), SCENE.to_vec()).await.unwrap();
    let e = engine.submit(&crate::users::Identity::anyone(), req.clone()).await.unwrap_err().to_string();
    assert!(e.contains("cannot denoise") && e.contains("no denoiser"), "{e}");
    assert!(on(&engine, |c| c.list_renders(0, 10, |_| true).0.is_empty()), "a refused render was stored");
    let mut raw = fixed();
    raw.setup.settings.features = true;
    let (plain, plain_id, _plain_dir) = straight(raw).await;
    let plain = tessera_film::read_exr_bytes(&plain.image(plain_id).await.unwrap(), "image").unwrap();
    for fails in [false, true] {
        let dir = fresh_dir("denoise");
        let denoiser = Ok(SharedDenoiser(Arc::new(Grey { fails })));
        let (engine, id) =
            submitted_as(CoreConfig { denoiser, ..CoreConfig::new(dir.path().to_path_buf()) }, req.clone()).await;
        work(&engine, &scene, usize::MAX).await;
        let written = tessera_film::read_exr_bytes(&engine.image(id).await.unwrap(), "image").unwrap();
        assert_eq!(
            (&written.rgb, &written.variance, &written.features),
            (&plain.rgb, &plain.variance, &plain.features)
        );
        if fails {
            assert_eq!(written.denoised, None);
            assert!(
                written.metadata.ends_with("denoiser=none: denoising failed: out of memory\n"),
                "{}",
                written.metadata
            );
            continue;
        }
        let grey: Vec<[f32; 3]> = plain.rgb.iter().map(|p| [(p[0] + p[1] + p[2]) / 3.0; 3]).collect();
        assert_eq!(written.denoised.as_ref(), Some(&grey));
        assert!(written.metadata.ends_with("denoiser=grey 1.0\n"), "{}", written.metadata);
        std::fs::remove_file(on(&engine, |c| c.image_path(id).unwrap().0)).unwrap();
        let rebuilt = tessera_film::read_exr_bytes(&engine.image(id).await.unwrap(), "image").unwrap();
        assert_eq!(rebuilt, written, "rebuilt from the stored results and denoised again");
    }
}
