//! Quality after submit: `tessera refine` (a finished render continued to more samples or a
//! lower target error), and an adaptive render's ETA, which runs to its predicted end.

use super::*;
use crate::core::Refinement;

fn samples(engine: &Engine, id: i64) -> u64 {
    on(engine, |c| c.status(id).unwrap().samples_done)
}

/// A finished render refined to more samples (fixed), or to a lower target error (adaptive),
/// with a coordinator restart halfway through the new passes, ends as the image of a render
/// submitted with that quality from the start, bit for bit, having rendered only the passes
/// the new quality adds.
#[tokio::test]
async fn a_refined_render_is_the_bits_of_one_submitted_with_its_new_quality() {
    let scene = furnace();
    let adaptive =
        |target_error| Submission { adaptive: Some(Adaptive { target_error, min_spp: 4 }), ..request(&hash()) };
    let cases = [
        (
            Submission { spp: 16, ..fixed() },
            Submission { spp: 64, ..fixed() },
            Refinement { spp: Some(64), target_error: None },
        ),
        (adaptive(0.1), adaptive(0.02), Refinement { spp: None, target_error: Some(0.02f32 as f64) }),
    ];
    for (before, after, to) in cases {
        let (direct, direct_id, _direct_dir) = straight(after).await;
        let want = direct.image(direct_id).await.unwrap();
        let dir = fresh_dir("refine");
        let (engine, id) = submitted_as(CoreConfig::new(dir.path().to_path_buf()), before).await;
        work(&engine, &scene, usize::MAX).await;
        assert_eq!(state(&engine, id), RenderState::Done);
        let first = samples(&engine, id);
        assert!(first < samples(&direct, direct_id), "{to:?}: the refinement would add nothing");
        engine.refine(Target::Render(id), to).await.unwrap();
        assert_eq!(state(&engine, id), RenderState::Running);
        assert_eq!(samples(&engine, id), first, "what it merged is kept");
        let mut rendered = 0;
        while let Some((job, sums)) = render_job(&engine, &scene).await {
            rendered += sums.pixels.iter().map(|p| p.n).sum::<u64>();
            assert_eq!(complete(&engine, &job, &sums).await.unwrap(), Outcome::Merged);
            if 2 * (first + rendered) >= first + samples(&direct, direct_id) {
                break; // a restart halfway through the new passes
            }
        }
        drop(engine);
        let engine = open(dir.path());
        assert_eq!(state(&engine, id), RenderState::Running, "a restart resumes the refinement");
        while let Some((job, sums)) = render_job(&engine, &scene).await {
            rendered += sums.pixels.iter().map(|p| p.n).sum::<u64>();
            assert_eq!(complete(&engine, &job, &sums).await.unwrap(), Outcome::Merged);
        }
        assert_eq!(first + rendered, samples(&direct, direct_id), "{to:?}: only the new passes were rendered");
        assert!(engine.image(id).await.unwrap() == want, "{to:?}: the refined image differs from the direct render's");
    }
}

/// Refinements that cannot give a direct render's bits, or change nothing, are refused saying
/// why, and leave the render as it was.
#[tokio::test]
async fn refinements_that_cannot_hold_are_refused() {
    let scene = furnace();
    let dir = fresh_dir("refine-refused");
    let (engine, id) = submitted_as(CoreConfig::new(dir.path().to_path_buf()), Submission { spp: 16, ..fixed() }).await;
    let refused = async |to: Refinement| engine.refine(Target::Render(id), to).await.unwrap_err().to_string();
    let more = Refinement { spp: Some(32), target_error: None };
    assert!(refused(more).await.contains("only a finished render"));
    work(&engine, &scene, usize::MAX).await;
    for (to, why) in [
        (Refinement { spp: Some(8), target_error: None }, "refining adds samples"),
        (Refinement { spp: Some(16), target_error: None }, "nothing to refine"),
        (Refinement { spp: None, target_error: Some(0.01) }, "fixed sample count"),
        (Refinement { spp: Some(1 << 30), target_error: None }, "over this coordinator's limit"),
    ] {
        let e = refused(to).await;
        assert!(e.contains(why), "{to:?}: {e}");
        assert_eq!(state(&engine, id), RenderState::Done);
    }
    assert_eq!(samples(&engine, id), 16 * 64 * 16, "the refused refinements changed nothing");
    // A render whose samples end in a part of a pass cannot take more bit for bit.
    let odd_dir = fresh_dir("refine-odd");
    let (odd, odd_id) =
        submitted_as(CoreConfig::new(odd_dir.path().to_path_buf()), Submission { spp: 18, ..fixed() }).await;
    work(&odd, &scene, usize::MAX).await;
    let e = odd.refine(Target::Render(odd_id), more).await.unwrap_err().to_string();
    assert!(e.contains("part of a 4-spp pass"), "{e}");
    // An adaptive render refines to a lower error, not a higher one.
    let up_dir = fresh_dir("refine-up");
    let adaptive = Submission { adaptive: Some(Adaptive { target_error: 0.1, min_spp: 4 }), ..request(&hash()) };
    let (up, up_id) = submitted_as(CoreConfig::new(up_dir.path().to_path_buf()), adaptive).await;
    work(&up, &scene, usize::MAX).await;
    let e = up
        .refine(Target::Render(up_id), Refinement { spp: None, target_error: Some(0.2) })
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("refining lowers it"), "{e}");
}

/// An adaptive render's ETA runs to the end its rounds are predicted to reach, not to the end
/// of the rounds decided so far: once every tile's first round is judged, the predicted passes
/// come within 30 % of where the render ends. Its quote (the dashboard's) predicts the same
/// samples, the render's end inside its range, at the speed of the worker that may take it.
#[tokio::test]
async fn an_adaptive_renders_eta_and_quote_run_to_its_predicted_end() {
    let scene = furnace();
    let dir = fresh_dir("eta");
    let (engine, id) = submitted(dir.path()).await;
    let tiles = on(&engine, |c| c.renders[&id].plan.tiles.len());
    let before = on(&engine, |c| c.forecast(id).unwrap());
    assert_eq!(
        (before.tiles_judged, before.samples, before.workers),
        (0, 64 * 16 * 64, 0),
        "at most, unjudged: {before:?}"
    );
    // The worker says its speed with its first request.
    let offer = crate::model::Offer { samples_per_second: 2e5, ..crate::model::Offer::plain("w") };
    let job = engine.lease(&offer, None, Duration::ZERO).await.unwrap().unwrap();
    let samples = RenderPlan::new(64, 16, 16, job.spp, job.pass_spp).samples(job.first_pass, job.pass_count);
    complete(&engine, &job, &render_tile(&scene, &job.setup.settings, job.tile, samples).unwrap()).await.unwrap();
    while on(&engine, |c| c.renders[&id].predicted.iter().filter(|p| p[0] > 0).count()) < tiles {
        work(&engine, &scene, 1).await;
    }
    let (expected, decided) = on(&engine, |c| (c.renders[&id].passes_expected(), c.renders[&id].passes_total));
    let info = on(&engine, |c| c.status(id).unwrap());
    let pixels = 16 * 16;
    let remaining = (expected - info.passes_done) as f64 * 4.0 * pixels as f64;
    assert!((info.eta_seconds * info.samples_per_second - remaining).abs() <= 1e-6 * remaining.max(1.0));
    let quote = on(&engine, |c| c.forecast(id).unwrap());
    assert_eq!((quote.tiles_judged, quote.samples), (tiles, expected * 4 * pixels), "{quote:?}");
    assert_eq!((quote.workers, quote.threads, quote.samples_per_second), (1, 1, 2e5));
    work(&engine, &scene, usize::MAX).await;
    let rendered = on(&engine, |c| c.status(id).unwrap().samples_done);
    assert!((quote.samples_low..=quote.samples_high).contains(&rendered), "{rendered} outside {quote:?}");
    assert!(on(&engine, |c| c.forecast(id)).is_none(), "a finished render has no quote");
    let end = on(&engine, |c| c.status(id).unwrap().passes_total);
    assert!(decided < end, "the first rounds alone reach the end ({decided} of {end} passes): nothing to predict");
    let ratio = expected as f64 / end as f64;
    assert!((0.7..=1.3).contains(&ratio), "predicted {expected} passes, the render ended with {end}");
}
