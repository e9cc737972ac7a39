//! Notifications as the core sees them: which URLs a render may ask to be told at (checked at
//! submit, by every door), and which renders and sequences ended and are to be told
//! ([`Core::take_ended`]); the HTTP door's notifier (`http/notify.rs`) sends them.

use super::{Core, Target, counts::Kind};
use crate::model::Ended;

/// Longest notification URL, in bytes.
pub const MAX_URL_BYTES: usize = 2048;

/// Where notifications may go and how they are signed (`tessera coordinator --notify-key
/// --notify-host --notify`).
#[derive(Clone, Debug, Default)]
pub struct NotifyConfig {
    /// The HMAC key; without one the coordinator sends no notifications (and refuses renders
    /// that ask for them).
    pub key: Option<Vec<u8>>,
    /// Hosts a notification URL may name; empty: any.
    pub hosts: Vec<String>,
    /// The URL of renders submitted without one (empty: none).
    pub default_url: String,
}

impl NotifyConfig {
    /// Refuses a URL notifications may not go to, saying why: not http or https, no host, too
    /// long or unprintable, a host not on the allow-list, or no key to sign with.
    pub fn check_url(&self, url: &str) -> Result<(), String> {
        if url.is_empty() {
            return Ok(());
        }
        if self.key.is_none() {
            return Err(
                "this coordinator sends no notifications: start it with --notify-key (or TESSERA_NOTIFY_KEY)".into()
            );
        }
        if url.len() > MAX_URL_BYTES
            || url.chars().any(|c| c.is_whitespace() || tessera_request::limits::unprintable(c))
        {
            return Err(format!(
                "the notification URL is over {MAX_URL_BYTES} bytes or holds spaces or control characters"
            ));
        }
        let scheme = url.split_once("://").map(|(s, _)| s.to_ascii_lowercase());
        if !matches!(scheme.as_deref(), Some("http" | "https")) {
            return Err(format!("'{url}' is not an http:// or https:// URL"));
        }
        let host = host_of(url).ok_or_else(|| format!("'{url}' names no host"))?;
        if !self.hosts.is_empty() && !self.hosts.iter().any(|h| h.eq_ignore_ascii_case(host)) {
            return Err(format!(
                "notifications may go only to {} (--notify-host), not to {host}",
                self.hosts.join(", ")
            ));
        }
        Ok(())
    }
}

/// The host a URL names (`http://user@host:port/path`: `host`; an IPv6 address without its
/// brackets), if it names one.
fn host_of(url: &str) -> Option<&str> {
    let rest = url.split_once("://")?.1;
    let authority = rest.split(['/', '?', '#']).next()?;
    let hostport = authority.rsplit_once('@').map_or(authority, |(_, h)| h);
    let host = match hostport.strip_prefix('[') {
        Some(v6) => v6.split_once(']')?.0,
        None => hostport.split(':').next()?,
    };
    (!host.is_empty()).then_some(host)
}

impl Core {
    /// The renders and sequences that ended since the last call, for the engine's notifier.
    pub fn take_ended(&mut self) -> Vec<Ended> {
        std::mem::take(&mut self.ended)
    }

    /// Render `id` stopped running (done, failed or cancelled): if it asked to be notified, it
    /// (or, for its sequence's last frame to stop, the sequence) is told.
    pub(super) fn tell_end(&mut self, id: i64) {
        let Some(stored) = self.renders.get(&id).map(|r| &r.stored).or_else(|| self.failed.get(&id)) else { return };
        if stored.notify.is_empty() {
            return;
        }
        let (url, sequence) = (stored.notify.clone(), stored.sequence);
        let target = match sequence {
            0 => Target::Render(id),
            seq => match self.counts.tallies.get(&seq) {
                Some(t) if t.count(Kind::Running) + t.count(Kind::Queued) == 0 => Target::Sequence(seq),
                _ => return,
            },
        };
        if let Some(info) = self.status_of(target) {
            self.ended.push(Ended { url, info });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn notification_urls_are_checked() {
        let config = NotifyConfig { key: Some(b"key".to_vec()), hosts: vec![], default_url: String::new() };
        assert!(config.check_url("https://hooks.example.com/tessera?x=1").is_ok());
        for (bad, says) in [
            ("ftp://example.com/", "not an http"),
            ("file:///etc/passwd", "not an http"),
            ("http://a b/", "spaces"),
            ("http:///nohost", "names no host"),
            ("http://user@/x", "names no host"),
        ] {
            let e = config.check_url(bad).unwrap_err();
            assert!(e.contains(says), "{bad}: {e}");
        }
        let long = format!("http://example.com/{}", "a".repeat(MAX_URL_BYTES));
        assert!(config.check_url(&long).unwrap_err().contains("over 2048 bytes"));
        let listed = NotifyConfig { hosts: vec!["hooks.example.com".into()], ..config.clone() };
        assert!(listed.check_url("http://hooks.example.com:8080/x").is_ok());
        assert!(listed.check_url("http://169.254.169.254/latest").unwrap_err().contains("may go only to"));
        let e = listed.check_url("http://hooks.example.com@169.254.169.254/").unwrap_err();
        assert!(e.contains("not to 169.254.169.254"), "the host after the user part counts: {e}");
        assert_eq!(host_of("https://[::1]:8443/x"), Some("::1"));
        let keyless = NotifyConfig::default();
        assert!(keyless.check_url("http://example.com/").unwrap_err().contains("--notify-key"));
        assert!(keyless.check_url("").is_ok(), "no URL, nothing to check");
    }
}
