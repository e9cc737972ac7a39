//! Per-user access: a token file (`--tokens FILE`) names who may call the coordinator and as
//! what. Each line is `NAME ROLE BLAKE3-OF-TOKEN [weight=W]` (`#` starts a comment); the file
//! holds hashes, never tokens. Roles: `submit` (renders of one's own: submit, watch, fetch,
//! cancel, retry, pause, priority, log), `admin` (every render), `worker` (the work service
//! only). The weight (default 1, up to 1000) is the user's share of the farm when several
//! users' renders wait. The file is read again on SIGHUP.

use std::collections::HashMap;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Role {
    Submit,
    Admin,
    Worker,
}

/// The name the shared `--token`'s renders are listed under; a token file may give it only to
/// an admin.
pub const SHARED_TOKEN_NAME: &str = "admin";

/// Who made a request (a request extension set by the token check).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Identity {
    pub name: String,
    pub role: Role,
}

impl Identity {
    /// The caller of a coordinator without tokens: may do everything, and has no name.
    pub fn anyone() -> Self {
        Self { name: String::new(), role: Role::Admin }
    }

    /// The holder of the shared `--token`: may do everything; its renders are listed as
    /// [`SHARED_TOKEN_NAME`]'s.
    pub fn shared_token() -> Self {
        Self { name: SHARED_TOKEN_NAME.into(), role: Role::Admin }
    }

    /// Whether this caller may see and act on a render owned by `owner`.
    pub fn may_touch(&self, owner: &str) -> bool {
        self.role == Role::Admin || self.name == owner
    }
}

/// The users of a token file, by the hash of their token.
#[derive(Clone, Debug, Default)]
pub struct Users {
    by_hash: HashMap<String, Identity>,
    /// Users' weights in the fair share, where the file gives one.
    weights: HashMap<String, f64>,
}

impl Users {
    /// Parses a token file; an error names the line.
    pub fn parse(text: &str) -> Result<Self, String> {
        let mut by_hash = HashMap::new();
        let mut weights = HashMap::new();
        let mut names = std::collections::HashSet::new();
        for (i, line) in text.lines().enumerate() {
            let line = line.split('#').next().unwrap_or("").trim();
            if line.is_empty() {
                continue;
            }
            let at = |m: String| format!("line {}: {m}", i + 1);
            let fields: Vec<&str> = line.split_whitespace().collect();
            let (name, role, hash, weight) = match fields[..] {
                [name, role, hash] => (name, role, hash, None),
                [name, role, hash, weight] => (name, role, hash, Some(weight)),
                _ => {
                    return Err(at(format!("expected NAME ROLE TOKEN-HASH [weight=W], found {} fields", fields.len())));
                }
            };
            if let Some(weight) = weight {
                let w = weight.strip_prefix("weight=").and_then(|w| w.parse::<f64>().ok());
                let Some(w) = w.filter(|w| w.is_finite() && *w > 0.0 && *w <= 1000.0) else {
                    return Err(at(format!("'{weight}' is not weight=W with W above 0 and up to 1000")));
                };
                weights.insert(name.to_string(), w);
            }
            let role = match role {
                "submit" => Role::Submit,
                "admin" => Role::Admin,
                "worker" => Role::Worker,
                other => return Err(at(format!("role '{other}' is not submit, admin or worker"))),
            };
            if name.len() > 64 || !name.bytes().all(|b| b.is_ascii_alphanumeric() || b"-_.@".contains(&b)) {
                return Err(at(format!("'{name}' is not a name (letters, digits, - _ . @; at most 64)")));
            }
            if hash.len() != 64 || !hash.bytes().all(|b| b.is_ascii_hexdigit()) {
                return Err(at(
                    "the token hash is not 64 hex digits (b3sum of the token, or `tessera token-hash`)".into()
                ));
            }
            if hash.eq_ignore_ascii_case(&token_hash("")) {
                return Err(at(format!(
                    "'{name}' has the hash of the empty token (what `printf '%s' \"$TOKEN\" | b3sum` gives when \
                     $TOKEN is unset), which would let an empty token in: hash a real token with `tessera token-hash`"
                )));
            }
            if name == SHARED_TOKEN_NAME && role != Role::Admin {
                return Err(at(format!(
                    "'{SHARED_TOKEN_NAME}' is the name the shared --token's renders are listed under: give this \
                     {} user another name",
                    fields[1]
                )));
            }
            if !names.insert(name.to_string()) {
                return Err(at(format!("'{name}' is listed twice")));
            }
            if by_hash.insert(hash.to_ascii_lowercase(), Identity { name: name.to_string(), role }).is_some() {
                return Err(at("this token hash is listed twice".into()));
            }
        }
        if by_hash.is_empty() {
            return Err("the token file names no user".into());
        }
        Ok(Self { by_hash, weights })
    }

    /// Users' weights in the fair share, where the file gives one (others weigh 1).
    pub fn weights(&self) -> HashMap<String, f64> {
        self.weights.clone()
    }

    /// Reads and parses a token file.
    pub fn load(path: &std::path::Path) -> Result<Self, String> {
        let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
        Self::parse(&text).map_err(|e| format!("{}: {e}", path.display()))
    }

    /// The user a presented token belongs to. A token no one may use (empty, short, unprintable:
    /// `tessera_proto::token::check_token`) belongs to no one, whatever the file lists.
    pub fn identify(&self, token: &str) -> Option<&Identity> {
        tessera_proto::token::check_token(token).ok()?;
        self.by_hash.get(&token_hash(token))
    }

    /// Users by token hash as given, unchecked: for tests of what the doors do with a file that
    /// got past the checks.
    #[cfg(test)]
    pub(crate) fn from_hashes(users: impl IntoIterator<Item = (String, Identity)>) -> Self {
        Self { by_hash: users.into_iter().collect(), weights: HashMap::new() }
    }

    pub fn len(&self) -> usize {
        self.by_hash.len()
    }

    pub fn is_empty(&self) -> bool {
        self.by_hash.is_empty()
    }
}

/// What a token file stores for a token: its BLAKE3 hash, hex.
pub fn token_hash(token: &str) -> String {
    blake3::hash(token.as_bytes()).to_hex().to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn token_files_parse_and_refuse_mistakes_by_line() {
        let alice = token_hash("alice-token-0123456789");
        let text = format!(
            "# who may call\nalice submit {alice}\n\nfarm worker {}  # the workers\n",
            token_hash("w-token-0123456789ab")
        );
        let users = Users::parse(&text).unwrap();
        assert_eq!(users.len(), 2);
        assert_eq!(
            users.identify("alice-token-0123456789"),
            Some(&Identity { name: "alice".into(), role: Role::Submit })
        );
        assert_eq!(users.identify("guess"), None);
        let weighted = Users::parse(&format!("alice submit {alice} weight=2.5")).unwrap();
        assert_eq!(weighted.weights().get("alice"), Some(&2.5));
        for (bad, says) in [
            (format!("alice boss {alice}"), "line 1: role 'boss'"),
            (format!("alice submit {alice}\nbob submit {alice}"), "line 2: this token hash is listed twice"),
            ("alice submit 1234".to_string(), "64 hex digits"),
            (format!("al ice submit {alice} x"), "expected NAME ROLE TOKEN-HASH"),
            (format!("alice submit {alice} weight=0"), "'weight=0' is not weight=W"),
            (format!("alice submit {alice} heavy"), "'heavy' is not weight=W"),
            ("# nobody".to_string(), "names no user"),
            (format!("eve admin {}", token_hash("")), "hash of the empty token"),
        ] {
            assert!(Users::parse(&bad).unwrap_err().contains(says), "{bad}: {:?}", Users::parse(&bad).err());
        }
    }

    /// No empty or short token is ever accepted, whatever the file lists: a file that lists the
    /// empty token's hash is refused, and one that got such a hash in anyway still lets nothing
    /// in for it.
    #[test]
    fn empty_and_short_tokens_belong_to_no_one() {
        let admin = Identity { name: "eve".into(), role: Role::Admin };
        let users = Users {
            by_hash: [token_hash(""), token_hash("short")]
                .into_iter()
                .map(|h| (h, admin.clone()))
                .chain([(token_hash("a-long-enough-token-0123"), admin.clone())])
                .collect(),
            weights: HashMap::new(),
        };
        assert_eq!(users.identify(""), None);
        assert_eq!(users.identify("short"), None);
        assert_eq!(users.identify("a-long-enough-token-0123"), Some(&admin));
    }
}
