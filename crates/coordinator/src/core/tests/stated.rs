//! A stated error on the farm (`--confidence`): tiles stop on their error bounds, the rounds
//! replay alike after a restart, and the image and `status` state the error with its bound.

use super::*;

/// The test render to a target its tiles reach inside their 64 spp, stating its error at
/// `confidence` (0: not).
fn stated(confidence: f32) -> Submission {
    let mut req = Submission { adaptive: Some(Adaptive { target_error: TARGET, min_spp: 4 }), ..request(&hash()) };
    req.setup.settings.confidence = confidence;
    req
}

const TARGET: f32 = 0.05;

fn budget(engine: &Engine, id: i64) -> Vec<u32> {
    on(engine, |c| c.renders[&id].budget.clone())
}

#[tokio::test]
async fn a_stated_error_rounds_on_its_bound_survives_a_restart_and_is_stated() {
    let scene = furnace();
    let (plain, plain_id, _plain_dir) = straight(stated(0.0)).await;
    let (direct, direct_id, _direct_dir) = straight(stated(0.95)).await;
    let (without, with) = (budget(&plain, plain_id), budget(&direct, direct_id));
    assert!(
        with.iter().zip(&without).all(|(w, p)| w >= p) && with != without,
        "the bound is above the estimate, so some tile goes on further: {with:?} against {without:?}"
    );
    let dir = fresh_dir("stated");
    let (id, before) = {
        let (engine, id) = submitted_as(CoreConfig::new(dir.path().to_path_buf()), stated(0.95)).await;
        work(&engine, &scene, 6).await;
        assert_eq!(state(&engine, id), RenderState::Running, "restart mid-render");
        let running = on(&engine, |c| c.status(id).unwrap());
        assert!(running.error_bound > running.error_estimate && running.error_estimate > 0.0, "{running:?}");
        (id, budget(&engine, id))
    };
    let engine = open(dir.path());
    assert_eq!(budget(&engine, id), before, "the rounds replay on the bound, as they were decided");
    work(&engine, &scene, usize::MAX).await;
    assert_eq!(state(&engine, id), RenderState::Done);
    assert_eq!(budget(&engine, id), with);
    let bytes = engine.image(id).await.unwrap();
    assert_eq!(bytes, direct.image(direct_id).await.unwrap(), "the same file as straight through");
    let done = on(&engine, |c| c.status(id).unwrap());
    assert!(done.confidence == 0.95 && done.error_bound > done.error_estimate, "{done:?}");
    let header = tessera_film::read_exr_bytes(&bytes, "the image").unwrap().metadata;
    let line = format!(
        "relative_error={:.6} error_bound={:.6} confidence=0.95 target_error=0.05",
        done.error_estimate, done.error_bound
    );
    assert!(header.lines().any(|l| l == line), "status and image state the same error: {line:?} in\n{header}");
    drop(engine);
    let reopened = on(&open(dir.path()), |c| c.status(id).unwrap());
    assert_eq!(
        (reopened.error_estimate, reopened.error_bound, reopened.confidence),
        (done.error_estimate, done.error_bound, done.confidence),
        "a finished render states its error and bound after a restart as before"
    );
    let plain_header =
        tessera_film::read_exr_bytes(&plain.image(plain_id).await.unwrap(), "the image").unwrap().metadata;
    assert!(!plain_header.contains("relative_error="), "a render without a confidence states nothing new");
}
