//! Bounded fuzzing of the glTF/GLB loader, seeded with the fixtures: each run mutates them
//! (bytes overwritten, ranges cut, copied or dropped, JSON numbers replaced by extreme ones) and
//! loads the result. A panic anywhere in Tessera's own code fails the test with its location
//! (this is a debug build: overflows panic); the glTF crate's own panics are what `load_bytes`
//! turns into errors, and are allowed. Every refusal must name the file. The seed is fixed, so
//! CI runs the same cases every time; a failure proptest shrinks and prints becomes a test.

mod common;

use proptest::prelude::*;
use std::cell::RefCell;
use tessera_scene::load_bytes_unguarded;

thread_local! {
    /// Where the last panic on this thread happened.
    static PANICKED_AT: RefCell<Option<String>> = const { RefCell::new(None) };
}

fn seeds() -> Vec<(String, Vec<u8>)> {
    let dir = common::fixtures_dir();
    [
        "Box/glTF-Binary/Box.glb",
        "BoxTextured/glTF-Binary/BoxTextured.glb",
        "CornellBox/glTF/CornellBox.gltf",
        "BoxAnimated/glTF-Binary/BoxAnimated.glb",
        "AnimatedMorphCube/glTF-Binary/AnimatedMorphCube.glb",
    ]
        .iter()
        .filter_map(|p| std::fs::read(dir.join(p)).ok().map(|b| (p.to_string(), b)))
        .chain(std::iter::once((
            "minimal.gltf".to_string(),
            br#"{"asset":{"version":"2.0"},"scene":0,"scenes":[{"nodes":[0]}],"nodes":[{"mesh":0,"children":[]}],
            "meshes":[{"primitives":[{"attributes":{"POSITION":0},"indices":1}]}],
            "accessors":[{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]},
                         {"bufferView":1,"componentType":5121,"count":3,"type":"SCALAR"}],
            "bufferViews":[{"buffer":0,"byteLength":36},{"buffer":0,"byteOffset":36,"byteLength":3}],
            "buffers":[{"byteLength":39,"uri":"data:application/octet-stream;base64,AAAAAAAAAAAAAAAAAACAPwAAAAAAAAAAAAAAAAAAgD8AAAAAAAEC"}]}"#
                .to_vec(),
        )))
        .collect()
}

#[derive(Clone, Debug)]
enum Mutation {
    Overwrite(prop::sample::Index, u8),
    Truncate(prop::sample::Index),
    Duplicate(prop::sample::Index, prop::sample::Index),
    Remove(prop::sample::Index, u8),
    /// Replaces the digits of a JSON number with an extreme value.
    Number(prop::sample::Index, &'static str),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    let extreme = prop::sample::select(vec![
        "-1",
        "0",
        "4294967295",
        "18446744073709551616",
        "1e39",
        "-0",
        "65535",
        "2147483648",
    ]);
    prop_oneof![
        2 => (any::<prop::sample::Index>(), any::<u8>()).prop_map(|(i, b)| Mutation::Overwrite(i, b)),
        1 => any::<prop::sample::Index>().prop_map(Mutation::Truncate),
        1 => (any::<prop::sample::Index>(), any::<prop::sample::Index>()).prop_map(|(a, b)| Mutation::Duplicate(a, b)),
        1 => (any::<prop::sample::Index>(), any::<u8>()).prop_map(|(i, n)| Mutation::Remove(i, n)),
        10 => (any::<prop::sample::Index>(), extreme).prop_map(|(i, v)| Mutation::Number(i, v)),
    ]
}

fn apply(bytes: &mut Vec<u8>, m: &Mutation) {
    if bytes.is_empty() {
        return;
    }
    match m {
        Mutation::Overwrite(i, b) => {
            let i = i.index(bytes.len());
            bytes[i] = *b;
        }
        Mutation::Truncate(i) => bytes.truncate(i.index(bytes.len())),
        Mutation::Duplicate(a, b) => {
            let (a, b) = (a.index(bytes.len()), b.index(bytes.len()));
            let (from, to) = (a.min(b), a.max(b).min(a.min(b) + 64));
            let copy = bytes[from..to].to_vec();
            bytes.splice(to..to, copy);
        }
        Mutation::Remove(i, n) => {
            let i = i.index(bytes.len());
            let end = (i + *n as usize).min(bytes.len());
            bytes.drain(i..end);
        }
        Mutation::Number(i, v) => {
            // The first run of digits at or after i, in the JSON (a GLB's first chunk).
            let json_end = match bytes.get(12..16) {
                Some(len) if bytes.starts_with(b"glTF") => {
                    (20 + u32::from_le_bytes([len[0], len[1], len[2], len[3]]) as usize).min(bytes.len())
                }
                _ => bytes.len(),
            };
            let json_start = if bytes.starts_with(b"glTF") { 20.min(json_end) } else { 0 };
            if json_start >= json_end {
                return;
            }
            let start = json_start + i.index(json_end - json_start);
            let Some(s) = (start..json_end).find(|&k| bytes[k].is_ascii_digit()) else { return };
            let e = (s..json_end).find(|&k| !bytes[k].is_ascii_digit()).unwrap_or(json_end);
            bytes.splice(s..e, v.bytes());
            // A GLB's chunk length follows its JSON, padded with spaces to four bytes.
            if bytes.starts_with(b"glTF") {
                let grown = v.len() as isize - (e - s) as isize;
                let new_len = (json_end - 20) as isize + grown;
                let pad = (4 - new_len.rem_euclid(4)) % 4;
                let at = (json_end as isize + grown) as usize;
                bytes.splice(at..at, std::iter::repeat_n(b' ', pad as usize));
                let chunk = ((new_len + pad) as u32).to_le_bytes();
                bytes[12..16].copy_from_slice(&chunk);
                let total = (bytes.len() as u32).to_le_bytes();
                bytes[8..12].copy_from_slice(&total);
            }
        }
    }
}

fn config() -> ProptestConfig {
    ProptestConfig {
        cases: 6000,
        failure_persistence: None,
        rng_seed: proptest::test_runner::RngSeed::Fixed(0x61f7_10ad),
        ..ProptestConfig::default()
    }
}

#[test]
fn mutated_scenes_never_panic_in_tessera_code() {
    let previous = std::panic::take_hook();
    std::panic::set_hook(Box::new(|info| {
        let at = info.location().map(|l| l.to_string()).unwrap_or_default();
        PANICKED_AT.with(|p| *p.borrow_mut() = Some(format!("{at}: {info}")));
    }));
    let seeds = seeds();
    assert!(seeds.len() >= 3, "the fixtures are missing");
    let mut runner = proptest::test_runner::TestRunner::new(config());
    let strategy = (0..seeds.len(), proptest::collection::vec(mutation(), 1..4));
    let result = runner.run(&strategy, |(seed, mutations)| {
        let (name, bytes) = &seeds[seed];
        let mut bytes = bytes.clone();
        for m in &mutations {
            apply(&mut bytes, m);
        }
        PANICKED_AT.with(|p| p.borrow_mut().take());
        let base = common::fixtures_dir().join(name);
        let base = base.parent();
        // Every animation plays, at a time inside their keys, so that mutated keys are sampled.
        let pose = tessera_scene::PoseAt { animation: tessera_scene::animation::Choice::All, time: 1.3 };
        match std::panic::catch_unwind(|| load_bytes_unguarded(&bytes, base, name, Some(&pose))) {
            Ok(Ok(_)) => {}
            Ok(Err(e)) => prop_assert!(e.to_string().contains(name.as_str()), "a refusal that names no file: {e}"),
            Err(_) => {
                let at = PANICKED_AT.with(|p| p.borrow_mut().take()).unwrap_or_default();
                // The glTF crate's panics are caught by `load_bytes` and reported as errors.
                let in_gltf_crate = at.contains("/gltf-") || at.contains("/gltf/");
                prop_assert!(in_gltf_crate, "a panic in Tessera's code on {name} after {mutations:?}: {at}");
            }
        }
        Ok(())
    });
    std::panic::set_hook(previous);
    if let Err(e) = result {
        panic!("{e}");
    }
}
