//! Where a render may run: a worker's pool and tags (`tessera worker --pool gpu --tag
//! site=paris`, with `cpus=N`, `mem=NG` and CPU features found at start), and a submission's
//! pool and requirements (`submit --pool gpu --require mem>=32G --require avx512f`).
//!
//! A render with a pool goes only to workers of that pool; one without goes to any worker,
//! after the renders of the worker's own pool. A requirement is `KEY` (the worker has a tag of
//! that key), `KEY=VALUE` (that exact tag) or `KEY>=AMOUNT` (a tag of that key whose amount is at
//! least it; amounts may end in K, M, G or T, powers of 1024).

/// Most tags a worker offers, and most requirements a submission makes.
pub const MAX_TAGS: usize = 32;
/// Longest pool name, tag key or tag value, in bytes.
pub const MAX_TAG_BYTES: usize = 64;
/// Most bytes a worker's tags, or a submission's requirements, take together: the coordinator
/// keeps them for each of up to 65,536 workers.
pub const MAX_TAGS_TOTAL_BYTES: usize = 1024;

/// Refuses more than [`MAX_TAGS`] texts, or more than [`MAX_TAGS_TOTAL_BYTES`] of them.
fn check_count(what: &str, texts: &[String]) -> Result<(), String> {
    check_size(what, texts.len(), texts.iter().map(String::len).sum())
}

/// Refuses tags given already parsed (a worker in the coordinator's own process) past the
/// limits [`parse_tags`] holds the wire's to.
pub fn check_tags(tags: &[Tag]) -> Result<(), String> {
    let bytes = tags.iter().map(|t| t.key.len() + t.value.as_ref().map_or(0, |v| v.len() + 1)).sum();
    check_size("tags", tags.len(), bytes)
}

fn check_size(what: &str, count: usize, bytes: usize) -> Result<(), String> {
    if count > MAX_TAGS || bytes > MAX_TAGS_TOTAL_BYTES {
        return Err(format!(
            "{count} {what} of {bytes} bytes, over the limit of {MAX_TAGS} and {MAX_TAGS_TOTAL_BYTES} bytes"
        ));
    }
    Ok(())
}

/// A pool name, a tag key or a tag value: letters, digits and `. _ - + :`, 1 to
/// [`MAX_TAG_BYTES`] bytes.
fn check_word(what: &str, word: &str) -> Result<(), String> {
    let allowed = |c: char| c.is_ascii_alphanumeric() || "._-+:".contains(c);
    if word.is_empty() || word.len() > MAX_TAG_BYTES || !word.chars().all(allowed) {
        return Err(format!(
            "{what} '{}' is not 1 to {MAX_TAG_BYTES} letters, digits and . _ - + :",
            crate::printable(word)
        ));
    }
    Ok(())
}

/// Refuses a pool name that is not empty (no pool) or a word.
pub fn check_pool(pool: &str) -> Result<(), String> {
    if pool.is_empty() { Ok(()) } else { check_word("the pool", pool) }
}

/// A worker's tag: `KEY` or `KEY=VALUE`.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Tag {
    pub key: String,
    pub value: Option<String>,
}

impl Tag {
    pub fn parse(text: &str) -> Result<Self, String> {
        let (key, value) = match text.split_once('=') {
            Some((k, v)) => (k, Some(v)),
            None => (text, None),
        };
        check_word("the tag's key", key)?;
        if let Some(v) = value {
            check_word("the tag's value", v)?;
        }
        Ok(Tag { key: key.to_string(), value: value.map(str::to_string) })
    }
}

impl std::fmt::Display for Tag {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.value {
            Some(v) => write!(f, "{}={v}", self.key),
            None => write!(f, "{}", self.key),
        }
    }
}

/// What a render requires of a worker's tags.
#[derive(Clone, Debug, PartialEq)]
pub enum Requirement {
    /// A tag with this key.
    Has(String),
    /// This exact tag.
    Is(String, String),
    /// A tag with this key whose amount is at least this.
    AtLeast(String, f64),
}

impl Requirement {
    pub fn parse(text: &str) -> Result<Self, String> {
        if let Some((key, amount)) = text.split_once(">=") {
            check_word("the requirement's key", key)?;
            let n = amount_of(amount).ok_or_else(|| {
                format!("'{}' is not an amount (a number, with K, M, G or T after it)", crate::printable(amount))
            })?;
            return Ok(Requirement::AtLeast(key.to_string(), n));
        }
        match Tag::parse(text).map_err(|e| format!("requirement '{}': {e}", crate::printable(text)))? {
            Tag { key, value: Some(v) } => Ok(Requirement::Is(key, v)),
            Tag { key, value: None } => Ok(Requirement::Has(key)),
        }
    }

    /// Whether a worker with `tags` meets it.
    pub fn met_by(&self, tags: &[Tag]) -> bool {
        match self {
            Requirement::Has(key) => tags.iter().any(|t| &t.key == key),
            Requirement::Is(key, value) => tags.iter().any(|t| &t.key == key && t.value.as_ref() == Some(value)),
            Requirement::AtLeast(key, least) => tags
                .iter()
                .any(|t| &t.key == key && t.value.as_deref().and_then(amount_of).is_some_and(|n| n >= *least)),
        }
    }
}

impl std::fmt::Display for Requirement {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Requirement::Has(key) => write!(f, "{key}"),
            Requirement::Is(key, value) => write!(f, "{key}={value}"),
            Requirement::AtLeast(key, n) => write!(f, "{key}>={n}"),
        }
    }
}

/// A number with an optional K, M, G or T (powers of 1024) after it.
fn amount_of(text: &str) -> Option<f64> {
    let text = text.trim();
    let (digits, scale) = match text.char_indices().last()? {
        (i, 'K' | 'k') => (&text[..i], 1024f64),
        (i, 'M' | 'm') => (&text[..i], 1024f64.powi(2)),
        (i, 'G' | 'g') => (&text[..i], 1024f64.powi(3)),
        (i, 'T' | 't') => (&text[..i], 1024f64.powi(4)),
        _ => (text, 1.0),
    };
    let n: f64 = digits.parse().ok()?;
    (n.is_finite() && n >= 0.0).then_some(n * scale)
}

/// Where a render may run: its pool (empty: any) and its requirements.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Placement {
    pub pool: String,
    pub requires: Vec<Requirement>,
}

impl Placement {
    /// From the wire: the pool and each requirement checked.
    pub fn parse(pool: &str, requires: &[String]) -> Result<Self, String> {
        check_pool(pool)?;
        check_count("requirements", requires)?;
        let requires = requires.iter().map(|r| Requirement::parse(r)).collect::<Result<_, _>>()?;
        Ok(Placement { pool: pool.to_string(), requires })
    }

    /// Whether a worker of `pool` with `tags` may take it.
    pub fn admits(&self, pool: &str, tags: &[Tag]) -> bool {
        (self.pool.is_empty() || self.pool == pool) && self.requires.iter().all(|r| r.met_by(tags))
    }

    /// Its requirements as written (for the store and listings).
    pub fn requirement_texts(&self) -> Vec<String> {
        self.requires.iter().map(ToString::to_string).collect()
    }

    /// What it asks for, in words: "pool gpu, mem>=34359738368" (empty: nothing).
    pub fn describe(&self) -> String {
        let pool = (!self.pool.is_empty()).then(|| format!("pool {}", self.pool));
        pool.into_iter().chain(self.requirement_texts()).collect::<Vec<_>>().join(", ")
    }
}

/// A worker's tags from the wire, each checked.
pub fn parse_tags(tags: &[String]) -> Result<Vec<Tag>, String> {
    check_count("tags", tags)?;
    tags.iter().map(|t| Tag::parse(t)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tags(list: &[&str]) -> Vec<Tag> {
        list.iter().map(|t| Tag::parse(t).unwrap()).collect()
    }

    #[test]
    fn requirements_match_tags_by_key_value_and_amount() {
        let worker = tags(&["avx512f", "mem=64G", "cpus=16", "site=paris"]);
        let meets = |r: &str| Requirement::parse(r).unwrap().met_by(&worker);
        assert!(meets("avx512f") && meets("site=paris") && meets("mem>=32G") && meets("mem>=64G") && meets("cpus>=16"));
        assert!(!meets("gpu") && !meets("site=lyon") && !meets("mem>=65G") && !meets("cpus>=17") && !meets("site>=1"));
        let p = Placement::parse("gpu", &["mem>=32G".into()]).unwrap();
        assert!(p.admits("gpu", &worker) && !p.admits("", &worker) && !p.admits("cpu", &worker));
        assert!(Placement::default().admits("anything", &[]), "no pool and no requirement: any worker");
        assert_eq!(p.describe(), "pool gpu, mem>=34359738368");
    }

    #[test]
    fn names_tags_and_requirements_are_bounded_and_printable() {
        for bad in ["", "a b", "x\u{1b}[31m", "é", &"k".repeat(65), "a=", "=b", "a=b=c"] {
            assert!(Tag::parse(bad).is_err(), "tag {bad:?}");
        }
        for bad in ["mem>=lots", "mem>=-1", ">=3", "mem>=3X"] {
            assert!(Requirement::parse(bad).is_err(), "requirement {bad:?}");
        }
        assert!(check_pool("").is_ok() && check_pool("gpu-a100").is_ok() && check_pool("gpu pool").is_err());
        let many: Vec<String> = (0..=MAX_TAGS).map(|i| format!("t{i}")).collect();
        assert!(parse_tags(&many).unwrap_err().contains("over the limit"));
        assert!(Placement::parse("", &many).unwrap_err().contains("over the limit"));
        // 17 tags of 64 + 1 + 64 bytes: under the count, over the bytes.
        let long: Vec<String> = (0..17).map(|i| format!("{:k<64}={}", i, "v".repeat(64))).collect();
        assert!(parse_tags(&long).unwrap_err().contains("1024 bytes"));
        let parsed: Vec<Tag> = long.iter().map(|t| Tag::parse(t).unwrap()).collect();
        assert!(check_tags(&parsed).unwrap_err().contains("1024 bytes"), "the same bound on parsed tags");
        assert!(check_tags(&parsed[..7]).is_ok());
    }
}
