//! What a worker says about itself when it asks for work: its pool and tags. Besides the tags
//! given (`--tag KEY=VALUE`), it finds its own at start: `cpus` (the threads it renders with),
//! `mem` (the machine's memory, in whole GiB, as `64G`) and the CPU features renders can use
//! (`avx2`, `fma`, `avx512f`). A tag given replaces a found one of the same key.

use tessera_request::placement::Tag;

/// The tags found on this machine for a worker of `threads` threads.
pub fn found(threads: usize) -> Vec<Tag> {
    let mut tags = vec![Tag { key: "cpus".into(), value: Some(threads.to_string()) }];
    if let Some(gib) = memory_gib() {
        tags.push(Tag { key: "mem".into(), value: Some(format!("{gib}G")) });
    }
    tags.extend(cpu_features().into_iter().map(|f| Tag { key: f.into(), value: None }));
    tags
}

/// `given` over `found`: a given tag replaces a found one of its key. Sorted by key.
pub fn merged(found: Vec<Tag>, given: &[Tag]) -> Vec<Tag> {
    let mut tags: Vec<Tag> = found.into_iter().filter(|f| !given.iter().any(|g| g.key == f.key)).collect();
    tags.extend(given.iter().cloned());
    tags.sort();
    tags.dedup();
    tags
}

/// The machine's memory in whole GiB, from /proc/meminfo (Linux).
fn memory_gib() -> Option<u64> {
    let info = std::fs::read_to_string("/proc/meminfo").ok()?;
    let kib: u64 =
        info.lines().find_map(|l| l.strip_prefix("MemTotal:"))?.trim().trim_end_matches("kB").trim().parse().ok()?;
    Some(kib / (1024 * 1024))
}

#[cfg(target_arch = "x86_64")]
fn cpu_features() -> Vec<&'static str> {
    let mut found = Vec::new();
    if std::arch::is_x86_feature_detected!("avx2") {
        found.push("avx2");
    }
    if std::arch::is_x86_feature_detected!("fma") {
        found.push("fma");
    }
    if std::arch::is_x86_feature_detected!("avx512f") {
        found.push("avx512f");
    }
    found
}

#[cfg(not(target_arch = "x86_64"))]
fn cpu_features() -> Vec<&'static str> {
    Vec::new()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn found_tags_are_valid_and_given_ones_replace_them() {
        let found = found(6);
        for t in &found {
            assert_eq!(Tag::parse(&t.to_string()).as_ref(), Ok(t), "a found tag is one a user could give");
        }
        assert!(found.contains(&Tag::parse("cpus=6").unwrap()));
        let given = [Tag::parse("cpus=2").unwrap(), Tag::parse("site=paris").unwrap()];
        let tags = merged(found, &given);
        assert!(tags.contains(&given[0]) && tags.contains(&given[1]));
        assert_eq!(tags.iter().filter(|t| t.key == "cpus").count(), 1);
    }
}
