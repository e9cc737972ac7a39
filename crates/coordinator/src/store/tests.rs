//! The store's tests: what it writes, reads back as it was written.

use super::*;
use tessera_proto::sums::encode_tile_sums;
use tessera_render::glam::Vec3;
use tessera_render::{Tile, TileSums};

fn render_row() -> StoredRender {
    StoredRender {
        id: 0,
        scene_hash: "abc".into(),
        scene_name: "box".into(),
        settings: vec![1, 2, 3],
        spp: 32,
        tile_size: 4,
        pass_spp: 16,
        priority: 0,
        state: "running".into(),
        target_error: 0.0,
        min_spp: 0,
        message: String::new(),
        owner: String::new(),
        sequence: 0,
        submitted_at: 0.0,
        started_at: 0.0,
        ended_at: 0.0,
        name: String::new(),
        paused: false,
        pool: String::new(),
        requires: String::new(),
        notify: String::new(),
        preview_every: 0,
        preview_spp: 0,
        preview_target: 0.0,
        final_error: [0.0; 2],
    }
}

fn sums(tile: Tile, v: f32) -> TileSums {
    let mut s = TileSums::new(tile);
    for p in &mut s.pixels {
        p.add_sample(Vec3::splat(v), false);
    }
    s
}

#[test]
fn results_survive_reopening_and_rebuild_the_same_film() {
    let scratch = tempfile::Builder::new().prefix("tessera-store-").tempdir().unwrap();
    let dir = scratch.path();
    let t0 = Tile { x0: 0, y0: 0, width: 4, height: 4 };
    let t1 = Tile { x0: 4, y0: 0, width: 4, height: 4 };
    let id;
    let expected;
    {
        let store = Store::open(dir, true).unwrap();
        store.apply(&Write::Scene { hash: "abc".into(), bytes: b"glTF...".to_vec(), owner: String::new() }).unwrap();
        assert!(store.has_scene("abc").unwrap() && !store.has_scene("def").unwrap());
        id = 1;
        store.apply(&Write::Renders(vec![StoredRender { id, ..render_row() }])).unwrap();
        assert_eq!(store.max_render_id().unwrap(), id);
        store.put_result(id, &StoredResult { tile: 0, first: 0, count: 2 }, &encode_tile_sums(&sums(t0, 0.5))).unwrap();
        store.put_result(id, &StoredResult { tile: 1, first: 0, count: 1 }, &encode_tile_sums(&sums(t1, 2.0))).unwrap();
        let mut film = Film::new(8, 4);
        film.merge_tile(&sums(t1, 2.0)).unwrap();
        film.merge_tile(&sums(t0, 0.5)).unwrap();
        expected = film;
    }
    let store = Store::open(dir, true).unwrap();
    let (film, ranges) = store.rebuild(id, Film::new(8, 4)).unwrap();
    assert_eq!(film, expected);
    assert_eq!(ranges.len(), 2);
    assert_eq!(store.renders().unwrap()[0].scene_name, "box");
    assert_eq!(store.scene("abc").unwrap().as_deref(), Some(&b"glTF..."[..]));
}

#[test]
fn a_result_is_stored_at_most_once() {
    let store = Store::in_memory().unwrap();
    store.apply(&Write::Scene { hash: "abc".into(), bytes: b"x".to_vec(), owner: String::new() }).unwrap();
    let id = 7;
    store.apply(&Write::Renders(vec![StoredRender { id, ..render_row() }])).unwrap();
    let t = Tile { x0: 0, y0: 0, width: 2, height: 2 };
    let r = StoredResult { tile: 0, first: 0, count: 1 };
    store.put_result(id, &r, &encode_tile_sums(&sums(t, 1.0))).unwrap();
    assert!(store.put_result(id, &r, &encode_tile_sums(&sums(t, 1.0))).is_err(), "the primary key refuses a duplicate");
    let state = Write::State { render: 99, state: "done", message: String::new() };
    assert!(matches!(store.apply(&state), Err(StoreError::NoSuchRender(99))));
}

/// A finished render's error reads back as it was written, an infinite bound (one pixel left
/// the estimate's noise unknown) included; a NaN, which SQLite would keep as NULL, reads 0.
#[test]
fn a_final_error_reads_back_as_written() {
    let store = Store::in_memory().unwrap();
    store.apply(&Write::Scene { hash: "abc".into(), bytes: b"x".to_vec(), owner: String::new() }).unwrap();
    store.apply(&Write::Renders(vec![StoredRender { id: 1, ..render_row() }])).unwrap();
    assert_eq!(store.renders().unwrap()[0].final_error, [0.0; 2], "none until it finishes");
    for error in [[0.012, 0.015], [0.25, f64::INFINITY], [f64::NAN, f64::NAN]] {
        store.apply(&Write::FinalError { render: 1, error }).unwrap();
        let read = store.renders().unwrap()[0].final_error;
        assert_eq!(read, error.map(|v| if v.is_nan() { 0.0 } else { v }), "{error:?}");
    }
}
