//! A submitted render's quote before the farm is committed to it: submitted paused, its pilot
//! renders on the farm (ahead of other work, though paused), the quote rests on every tile of
//! it, and once resumed the render ends on the same bits as one never quoted.

use super::steer::log;
use super::*;

#[tokio::test]
async fn a_paused_renders_pilot_runs_on_the_farm_and_the_render_ends_on_the_same_bits() {
    let dir = fresh_dir("pilot");
    let scene = furnace();
    let paused = Submission { paused: true, ..request(&hash()) };
    let id = {
        let (engine, id) = submitted_as(CoreConfig::new(dir.path().to_path_buf()), paused.clone()).await;
        // Other work waits in line before it: the pilot still goes first.
        let other = engine.submit(&crate::users::Identity::anyone(), fixed()).await.unwrap().id();
        let info = on(&engine, |c| c.status(id).unwrap());
        assert!(info.paused && info.state == RenderState::Running, "submitted paused: {info:?}");
        assert_eq!(on(&engine, |c| c.forecast(id).unwrap().tiles_judged), 0);
        assert_eq!(engine.pilot(Target::Render(id), "alice").await.unwrap(), (id, 4), "its four tiles");
        assert!(log(&engine, Target::Render(id)).await.iter().any(|l| l.contains("quote asked by alice")));
        // The first round is one pass of 4 spp a tile: four jobs, all of the quoted render.
        for _ in 0..4 {
            let (job, sums) = render_job(&engine, &scene).await.unwrap();
            assert_eq!((job.render_id, job.first_pass, job.pass_count), (id, 0, 1), "the pilot first");
            assert_eq!(complete(&engine, &job, &sums).await.unwrap(), Outcome::Merged);
        }
        let quote = on(&engine, |c| c.forecast(id).unwrap());
        assert_eq!((quote.tiles_judged, quote.tiles, quote.samples_done), (4, 4, 64 * 16 * 4), "{quote:?}");
        assert!(quote.samples_low <= quote.samples && quote.samples <= quote.samples_high, "{quote:?}");
        assert_eq!(engine.pilot(Target::Render(id), "").await.unwrap(), (id, 0), "nothing left to judge");
        // Its pilot done, the paused render waits: the other render's jobs come next.
        let (job, _) = render_job(&engine, &scene).await.unwrap();
        assert_eq!(job.render_id, other);
        assert!(on(&engine, |c| c.status(id).unwrap().paused));
        id
    };
    // The judged tiles and their predictions outlive a restart.
    let engine = open(dir.path());
    assert_eq!(on(&engine, |c| c.forecast(id).unwrap().tiles_judged), 4);
    engine.steer(Target::Render(id), Steer { paused: Some(false), ..Steer::default() }, "").await.unwrap();
    work(&engine, &scene, usize::MAX).await;
    assert_eq!(state(&engine, id), RenderState::Done);
    let (straight, id2, _dir) = straight(request(&hash())).await;
    assert_eq!(straight.image(id2).await.unwrap(), engine.image(id).await.unwrap(), "images differ");
}

/// A quote is refused, saying why, for a render with nothing to pilot: a fixed budget, or a
/// render no longer running; a sequence's quote is its first running frame's.
#[tokio::test]
async fn a_quote_is_for_a_running_adaptive_render_and_a_sequences_is_its_first_frames() {
    let dir = fresh_dir("pilot-refused");
    let (engine, id) = submitted_as(CoreConfig::new(dir.path().to_path_buf()), fixed()).await;
    let e = engine.pilot(Target::Render(id), "").await.unwrap_err().to_string();
    assert!(e.contains("fixed number of samples"), "{e}");
    engine.cancel(Target::Render(id)).await.unwrap();
    let e = engine.pilot(Target::Render(id), "").await.unwrap_err().to_string();
    assert!(e.contains("is cancelled") && e.contains("only a queued or running render"), "{e}");
    let e = engine.pilot(Target::Render(99), "").await.unwrap_err().to_string();
    assert!(e.contains("no render 99"), "{e}");
    let list = Some(Frames { list: FrameList::parse("1-3").unwrap(), fps: 24.0 });
    let frames = Submission { frames: list, paused: true, ..request(&hash()) };
    let seq = engine.submit(&crate::users::Identity::anyone(), frames).await.unwrap();
    let first = on(&engine, |c| c.members(seq)[0]);
    assert_eq!(engine.pilot(seq, "").await.unwrap(), (first, 4));
    let (job, _) = render_job(&engine, &furnace()).await.unwrap();
    assert_eq!(job.render_id, first, "the paused sequence's first frame pilots");
}
