//! Steering after submit: pause and resume (kept over a restart, the image the same bits as a
//! render never paused), a pause that hands its jobs back at once, and priorities changed on
//! a running farm.

use super::*;

fn pause(now: bool) -> Steer {
    Steer { paused: Some(true), now, ..Steer::default() }
}

/// The lines of `target`'s stored log.
pub(crate) async fn log(engine: &Engine, target: Target) -> Vec<String> {
    engine.log(target, 0, 1000).await.unwrap().lines.into_iter().map(|l| l.line).collect()
}

fn resume() -> Steer {
    Steer { paused: Some(false), ..Steer::default() }
}

/// A paused render gets no jobs (its job in flight still merges), stays paused over a restart,
/// and once resumed finishes to the same bits as one never paused.
#[tokio::test]
async fn a_paused_render_waits_over_a_restart_and_resumes_to_the_same_bits() {
    let dir = fresh_dir("pause");
    let scene = furnace();
    let id = {
        let (engine, id) = submitted_as(CoreConfig::new(dir.path().to_path_buf()), fixed()).await;
        work(&engine, &scene, 3).await;
        let (job, sums) = render_job(&engine, &scene).await.unwrap();
        engine.steer(Target::Render(id), pause(false), "alice").await.unwrap();
        assert!(render_job(&engine, &scene).await.is_none(), "a paused render gets no job");
        assert_eq!(complete(&engine, &job, &sums).await.unwrap(), Outcome::Merged, "the job in flight merges");
        let info = on(&engine, |c| c.status(id).unwrap());
        assert!(info.paused && info.state == RenderState::Running && info.eta_seconds == 0.0, "{info:?}");
        assert!(log(&engine, Target::Render(id)).await.iter().any(|l| l.contains("paused by alice")));
        id
    };
    let engine = open(dir.path());
    assert!(on(&engine, |c| c.status(id).unwrap().paused), "still paused after a restart");
    assert!(render_job(&engine, &scene).await.is_none());
    engine.steer(Target::Render(id), resume(), "alice").await.unwrap();
    assert!(!on(&engine, |c| c.status(id).unwrap().paused));
    work(&engine, &scene, usize::MAX).await;
    assert_eq!(state(&engine, id), RenderState::Done);
    let (straight, id2, _dir) = straight(fixed()).await;
    assert_eq!(straight.image(id2).await.unwrap(), engine.image(id).await.unwrap(), "images differ");
    let e = engine.steer(Target::Render(id), pause(false), "").await.unwrap_err().to_string();
    assert!(e.contains("is done") && e.contains("only a queued or running render"), "{e}");
}

/// `pause --now` hands the jobs in flight back: their results are ignored, and the passes are
/// rendered again after the resume, to the same bits.
#[tokio::test]
async fn a_pause_now_hands_back_its_jobs_and_the_image_is_the_same() {
    let dir = fresh_dir("pause-now");
    let scene = furnace();
    let (engine, id) = submitted_as(CoreConfig::new(dir.path().to_path_buf()), fixed()).await;
    work(&engine, &scene, 2).await;
    let (job, sums) = render_job(&engine, &scene).await.unwrap();
    engine.steer(Target::Render(id), pause(true), "").await.unwrap();
    assert_eq!(complete(&engine, &job, &sums).await.unwrap(), Outcome::Ignored(Ignored::Released));
    assert!(log(&engine, Target::Render(id)).await.iter().any(|l| l.contains("1 job(s) in flight handed back")));
    engine.steer(Target::Render(id), resume(), "").await.unwrap();
    work(&engine, &scene, usize::MAX).await;
    let (straight, id2, _dir) = straight(fixed()).await;
    assert_eq!(straight.image(id2).await.unwrap(), engine.image(id).await.unwrap(), "images differ");
}

/// A sequence is paused and reprioritised as a whole (a frame alone is refused, saying what to
/// name); a priority set after submit orders the next lease, is kept over a restart, and is
/// held to its documented range.
#[tokio::test]
async fn priorities_change_the_order_at_the_next_lease_and_sequences_steer_as_one() {
    let dir = fresh_dir("priority");
    let scene = furnace();
    let (id, seq) = {
        let (engine, id) = submitted_as(CoreConfig::new(dir.path().to_path_buf()), fixed()).await;
        let seq = sequence(&engine).await;
        let first = on(&engine, |c| c.members(Target::Sequence(seq))[0]);
        let e = engine.steer(Target::Render(first), pause(false), "").await.unwrap_err().to_string();
        assert!(e.contains(&format!("frame of sequence s{seq}")), "{e}");
        // The still was submitted first: it goes first, until the sequence is raised.
        assert_eq!(render_job(&engine, &scene).await.unwrap().0.render_id, id);
        let raise = Steer { priority: Some(7), ..Steer::default() };
        engine.steer(Target::Sequence(seq), raise, "").await.unwrap();
        assert_ne!(render_job(&engine, &scene).await.unwrap().0.render_id, id, "the sequence goes first");
        assert_eq!(on(&engine, |c| c.status_of(Target::Sequence(seq)).unwrap().priority), 7);
        engine.steer(Target::Sequence(seq), pause(false), "").await.unwrap();
        assert!(on(&engine, |c| c.status_of(Target::Sequence(seq)).unwrap().paused));
        assert!(on(&engine, |c| c.status(first).unwrap().paused), "its frames show it");
        assert_eq!(render_job(&engine, &scene).await.unwrap().0.render_id, id, "the paused sequence waits");
        let high = Steer { priority: Some(1001), ..Steer::default() };
        let e = engine.steer(Target::Render(id), high, "").await.unwrap_err().to_string();
        assert!(e.contains("-1000..=1000"), "{e}");
        (id, seq)
    };
    let engine = open(dir.path());
    let info = on(&engine, |c| c.status_of(Target::Sequence(seq)).unwrap());
    assert!(info.paused && info.priority == 7, "kept over a restart: {info:?}");
    assert_eq!(render_job(&engine, &scene).await.unwrap().0.render_id, id);
    engine.steer(Target::Sequence(seq), resume(), "").await.unwrap();
    assert_ne!(render_job(&engine, &scene).await.unwrap().0.render_id, id, "resumed, priority 7 first");
}

/// A render's log is stored: it survives a restart and names a failed job's worker with its
/// error text (escaped: a worker's text never reaches a terminal raw); a sequence's log has
/// its own lines and its frames'.
#[tokio::test]
async fn the_log_survives_a_restart_and_names_a_failures_worker() {
    let dir = fresh_dir("log");
    let scene = furnace();
    let (id, seq) = {
        let (engine, id) = submitted_as(CoreConfig::new(dir.path().to_path_buf()), fixed()).await;
        let seq = sequence(&engine).await;
        let job = engine.lease(&Offer::plain("gpu-7"), None, Duration::ZERO).await.unwrap().unwrap();
        engine.fail("gpu-7", &job.lease_id.to_string(), "out of memory \u{1b}[31m").unwrap();
        engine.steer(Target::Sequence(seq), Steer { priority: Some(2), ..Steer::default() }, "bob").await.unwrap();
        work(&engine, &scene, 2).await;
        (id, seq)
    };
    let engine = open(dir.path());
    let lines = log(&engine, Target::Render(id)).await;
    assert!(lines[0].starts_with("submitted by anyone"), "{lines:?}");
    let failure = lines.iter().find(|l| l.contains("a job failed")).expect("the failure is logged");
    assert!(failure.contains("worker gpu-7: out of memory") && !failure.contains('\u{1b}'), "{failure}");
    let sequence_log = log(&engine, Target::Sequence(seq)).await;
    assert!(sequence_log[0].starts_with("submitted by anyone: 3 frames"), "{sequence_log:?}");
    assert!(sequence_log.iter().any(|l| l == "priority set to 2 by bob"), "{sequence_log:?}");
}

/// A render of a pool waits for a worker of it, saying so while only others are connected;
/// its placement is kept over a restart; a worker of the pool whose tags meet its requirement
/// takes it.
#[tokio::test]
async fn a_render_of_a_pool_waits_for_its_workers_and_says_so() {
    use tessera_request::placement::{Placement, Tag};
    let dir = fresh_dir("pool");
    let placement = Placement::parse("gpu", &["mem>=16G".into()]).unwrap();
    let (engine, id) =
        submitted_as(CoreConfig::new(dir.path().to_path_buf()), Submission { placement, ..fixed() }).await;
    assert!(engine.lease(&Offer::plain("cpu-box"), None, Duration::ZERO).await.unwrap().is_none());
    let info = on(&engine, |c| c.status(id).unwrap());
    assert!(info.no_worker_fits && info.placement == "pool gpu, mem>=17179869184", "{info:?}");
    let small = Offer { pool: "gpu".into(), tags: vec![Tag::parse("mem=8G").unwrap()], ..Offer::plain("small-gpu") };
    assert!(engine.lease(&small, None, Duration::ZERO).await.unwrap().is_none(), "8G is not 16G");
    drop(engine);
    let engine = open(dir.path());
    let big = Offer { pool: "gpu".into(), tags: vec![Tag::parse("mem=64G").unwrap()], ..Offer::plain("big-gpu") };
    assert!(engine.lease(&Offer::plain("cpu-box"), None, Duration::ZERO).await.unwrap().is_none(), "after a restart");
    let job = engine.lease(&big, None, Duration::ZERO).await.unwrap().expect("the gpu worker takes it");
    assert_eq!(job.render_id, id);
    assert!(!on(&engine, |c| c.status(id).unwrap().no_worker_fits));
}

/// A sequence of frames `frames` of the test render at `spp`, with previews first or not.
async fn previewed_sequence(
    engine: &Engine,
    frames: &str,
    spp: u32,
    preview: Option<tessera_request::PreviewFirst>,
) -> i64 {
    let mut req = Submission { spp, preview, ..fixed() };
    req.frames = Some(Frames { list: FrameList::parse(frames).unwrap(), fps: 24.0 });
    req.setup.pose = Some(Pose::default());
    match engine.submit(&crate::users::Identity::anyone(), req).await.unwrap() {
        Target::Sequence(id) => id,
        t => panic!("a sequence was submitted, {t} came back"),
    }
}

/// Previews first: while a sequence previews, only its preview frames' first passes are handed
/// out (every 2nd frame of 1-4 to 4 spp: one pass of each tile), their preview images are
/// written, and then every frame goes on; a restart mid-preview goes on previewing; every
/// frame is the same bits as in a sequence submitted without previews.
#[tokio::test]
async fn previews_come_first_and_change_no_bit_of_the_frames() {
    let scene = furnace();
    let submit = async |engine: &Engine, preview| previewed_sequence(engine, "1-4", 16, preview).await;
    let dir = fresh_dir("previews");
    let preview = Some(tessera_request::PreviewFirst { every: 2, spp: 3, target_error: 0.0 });
    let (engine, _) = submitted_as(CoreConfig::new(dir.path().to_path_buf()), fixed()).await;
    engine.cancel(Target::Render(1)).await.unwrap();
    let seq = submit(&engine, preview).await;
    let previews = [seq, seq + 2];
    // Half the preview jobs, a restart, the other half: only first passes of preview frames.
    let preview_jobs = async |engine: &Arc<Engine>| {
        for _ in 0..4 {
            let (job, sums) = render_job(engine, &scene).await.expect("a preview job");
            assert!(previews.contains(&job.render_id) && job.first_pass == 0 && job.pass_count == 1, "{job:?}");
            complete(engine, &job, &sums).await.unwrap();
        }
    };
    preview_jobs(&engine).await;
    drop(engine);
    let engine = open(dir.path());
    preview_jobs(&engine).await;
    let (previewed, n) = on(&engine, |c| c.previewed_frames(seq, 0, 10));
    assert_eq!(n, 2, "both previews written: {previewed:?}");
    assert!(previews.iter().all(|&id| dir.path().join(format!("renders/{id}.preview.exr")).is_file()));
    let log = log(&engine, Target::Sequence(seq)).await;
    assert!(log.iter().any(|l| l == "previews done (4 spp): every frame goes on"), "{log:?}");
    work(&engine, &scene, usize::MAX).await;
    let straight_dir = fresh_dir("previews-straight");
    let (straight, _) = submitted_as(CoreConfig::new(straight_dir.path().to_path_buf()), fixed()).await;
    straight.cancel(Target::Render(1)).await.unwrap();
    let plain = submit(&straight, None).await;
    work(&straight, &scene, usize::MAX).await;
    for k in 0..4 {
        assert_eq!(state(&engine, seq + k), RenderState::Done);
        let (a, b) = (engine.image(seq + k).await.unwrap(), straight.image(plain + k).await.unwrap());
        assert!(a == b, "frame {k} differs from the sequence without previews");
    }
    let preview = engine.preview_image(seq).await.unwrap();
    assert!(preview != engine.image(seq).await.unwrap(), "the preview is the 4-spp image");
    assert!(engine.preview_image(seq + 1).await.is_err(), "frame 2 has no preview");
}

/// Previews to a target error: preview frames get passes until their error estimate is down to
/// it (then none), other frames none; then every frame goes on, to the same bits as without.
#[tokio::test]
async fn previews_to_a_target_error_come_first_and_change_no_bit() {
    let scene = furnace();
    let submit = async |engine: &Engine, preview| previewed_sequence(engine, "1-3", 64, preview).await;
    let dir = fresh_dir("previews-error");
    let (engine, _) = submitted_as(CoreConfig::new(dir.path().to_path_buf()), fixed()).await;
    engine.cancel(Target::Render(1)).await.unwrap();
    let seq = submit(&engine, Some(tessera_request::PreviewFirst { every: 2, spp: 0, target_error: 0.2 })).await;
    let mut jobs = 0;
    while !log(&engine, Target::Sequence(seq))
        .await
        .iter()
        .any(|l| l == "previews done (error 0.2): every frame goes on")
    {
        let (job, sums) = render_job(&engine, &scene).await.expect("a preview job");
        assert!(job.render_id == seq || job.render_id == seq + 2, "only preview frames: {job:?}");
        complete(&engine, &job, &sums).await.unwrap();
        jobs += 1;
        assert!(jobs < 64, "the previews never reached their error");
    }
    for id in [seq, seq + 2] {
        let e = on(&engine, |c| c.status(id).unwrap().error_estimate);
        assert!(e <= 0.2, "frame {id}'s preview stopped at {e}");
    }
    work(&engine, &scene, usize::MAX).await;
    let plain_dir = fresh_dir("previews-error-plain");
    let (plain_engine, _) = submitted_as(CoreConfig::new(plain_dir.path().to_path_buf()), fixed()).await;
    plain_engine.cancel(Target::Render(1)).await.unwrap();
    let plain = submit(&plain_engine, None).await;
    work(&plain_engine, &scene, usize::MAX).await;
    for k in 0..3 {
        assert!(engine.image(seq + k).await.unwrap() == plain_engine.image(plain + k).await.unwrap(), "frame {k}");
    }
}
