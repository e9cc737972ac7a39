//! Notifications: when a render, or a whole sequence, finishes, fails or is cancelled, the
//! coordinator POSTs a JSON event to the URL it was submitted with (`submit --notify URL`, or
//! the coordinator's `--notify URL` default), signed with HMAC-SHA256 over the body under the
//! coordinator's `--notify-key` (header `X-Tessera-Signature: sha256=HEX`, as GitHub's
//! webhooks sign theirs). The core decides the events and which URLs are allowed
//! (`core/notify.rs`); a thread of its own sends them, retrying a receiver that is down or answers an error with a growing delay for
//! [`RETRY_FOR`], so that nothing on the lease path ever waits for one. Redirects are not
//! followed (they would lead past the allow-list). Events waiting are held in memory: a
//! coordinator that stops drops them (its log says how many).

use hmac::{Hmac, Mac};
use sha2::Sha256;
use std::collections::BinaryHeap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// How long an event is retried before it is given up.
pub const RETRY_FOR: Duration = Duration::from_secs(600);
/// The longest wait between two tries of one event.
const LONGEST_DELAY: Duration = Duration::from_secs(60);
/// Events waiting to be sent, at most; more are dropped (and counted).
const QUEUED: usize = 10_000;

/// An event to send: where, what (`done`, `failed`, `cancelled`), and its JSON body.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Notice {
    pub url: String,
    pub event: &'static str,
    pub body: String,
}

/// The event of a render or sequence that ended, as its receiver gets it: `event` (`done`,
/// `failed`, `cancelled`), `id` (`s` and a number for a sequence), its name, scene, owner,
/// message, when (seconds since the Unix epoch), its passes and samples, its error estimate
/// (with its bound and confidence, for a stated error), and a sequence's frames by state.
pub fn notice(ended: crate::model::Ended) -> Notice {
    let i = ended.info;
    let event = i.state.name();
    let mut body = serde_json::json!({
        "event": event,
        "id": i.render_id,
        "name": i.name,
        "scene": i.scene_name,
        "owner": i.owner,
        "message": i.message,
        "at": i.ended_at,
        "passes_done": i.passes_done,
        "passes_total": i.passes_total,
        "samples_done": i.samples_done,
        "error_estimate": i.error_estimate,
    });
    if i.confidence > 0.0 {
        // A stated error (`--confidence`): the true error is below the bound with that confidence.
        body["error_bound"] = serde_json::json!(i.error_bound);
        body["confidence"] = serde_json::json!(i.confidence);
    }
    if i.frames_total > 0 {
        body["frames"] = serde_json::json!({
            "total": i.frames_total,
            "done": i.frames_done,
            "failed": i.frames_failed,
            "cancelled": i.frames_total - i.frames_done - i.frames_failed - i.frames_running - i.frames_queued,
        });
    }
    Notice { url: ended.url, event, body: body.to_string() }
}

/// Notifications sent, given up and dropped (the queue full), since start.
#[derive(Debug, Default)]
pub struct NotifyCounts {
    pub sent: AtomicU64,
    pub failed: AtomicU64,
    pub dropped: AtomicU64,
}

/// The sending thread's door: events go in without waiting.
pub struct Notifier {
    queue: std::sync::mpsc::SyncSender<Notice>,
    pub counts: Arc<NotifyCounts>,
}

impl Notifier {
    /// Starts the sending thread, signing with `key`.
    pub fn start(key: Vec<u8>) -> std::io::Result<Self> {
        let (queue, events) = std::sync::mpsc::sync_channel(QUEUED);
        let counts = Arc::new(NotifyCounts::default());
        let sender = Sender { key, counts: counts.clone(), agent: agent() };
        std::thread::Builder::new().name("tessera-notify".into()).spawn(move || sender.run(events))?;
        Ok(Notifier { queue, counts })
    }

    /// Queues `notice`; a full queue drops it (counted and logged).
    pub fn send(&self, notice: Notice) {
        if self.queue.try_send(notice).is_err() {
            self.counts.dropped.fetch_add(1, Ordering::Relaxed);
            tracing::warn!("a notification was dropped: {QUEUED} are waiting to be sent");
        }
    }
}

/// The HMAC-SHA256 of `body` under `key`, as the signature header writes it.
pub fn signature(key: &[u8], body: &[u8]) -> String {
    let mut mac = Hmac::<Sha256>::new_from_slice(key).expect("HMAC takes a key of any length");
    mac.update(body);
    let bytes = mac.finalize().into_bytes();
    format!("sha256={}", bytes.iter().map(|b| format!("{b:02x}")).collect::<String>())
}

fn agent() -> ureq::Agent {
    ureq::Agent::config_builder()
        .timeout_global(Some(Duration::from_secs(10)))
        .max_redirects(0)
        .http_status_as_error(false)
        .build()
        .into()
}

/// An event waiting for its next try.
struct Waiting {
    due: Instant,
    first: Instant,
    tries: u32,
    order: u64,
    notice: Notice,
}

impl PartialEq for Waiting {
    fn eq(&self, other: &Self) -> bool {
        (self.due, self.order) == (other.due, other.order)
    }
}
impl Eq for Waiting {}
impl PartialOrd for Waiting {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Waiting {
    /// The earliest due first (the heap is a max-heap).
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        (other.due, other.order).cmp(&(self.due, self.order))
    }
}

struct Sender {
    key: Vec<u8>,
    counts: Arc<NotifyCounts>,
    agent: ureq::Agent,
}

impl Sender {
    fn run(self, events: std::sync::mpsc::Receiver<Notice>) {
        let mut waiting = BinaryHeap::new();
        let mut order = 0u64;
        loop {
            let wait = waiting.peek().map(|w: &Waiting| w.due.saturating_duration_since(Instant::now()));
            let received = match wait {
                Some(wait) => events.recv_timeout(wait),
                None => events.recv().map_err(|_| std::sync::mpsc::RecvTimeoutError::Disconnected),
            };
            match received {
                Ok(notice) => {
                    order += 1;
                    let now = Instant::now();
                    waiting.push(Waiting { due: now, first: now, tries: 0, order, notice });
                }
                Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
                Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => {
                    if !waiting.is_empty() {
                        tracing::warn!("{} notification(s) not sent: the coordinator stopped", waiting.len());
                    }
                    return;
                }
            }
            while waiting.peek().is_some_and(|w| w.due <= Instant::now()) {
                let Some(mut w) = waiting.pop() else { break };
                match self.post(&w.notice) {
                    Ok(()) => {
                        self.counts.sent.fetch_add(1, Ordering::Relaxed);
                    }
                    Err(e) if w.first.elapsed() < RETRY_FOR => {
                        w.tries += 1;
                        let delay = Duration::from_secs(1 << w.tries.min(6)).min(LONGEST_DELAY);
                        tracing::info!(url = %w.notice.url, "notification not delivered ({e}): trying again in {delay:?}");
                        w.due = Instant::now() + delay;
                        waiting.push(w);
                    }
                    Err(e) => {
                        self.counts.failed.fetch_add(1, Ordering::Relaxed);
                        tracing::warn!(url = %w.notice.url, "notification given up after {} tries: {e}", w.tries + 1);
                    }
                }
            }
        }
    }

    /// One try: a 2xx answer delivers it.
    fn post(&self, notice: &Notice) -> Result<(), String> {
        let answer = self
            .agent
            .post(&notice.url)
            .header("content-type", "application/json")
            .header("x-tessera-event", notice.event)
            .header("x-tessera-signature", signature(&self.key, notice.body.as_bytes()))
            .send(notice.body.as_bytes())
            .map_err(|e| e.to_string())?;
        match answer.status().as_u16() {
            200..=299 => Ok(()),
            code => Err(format!("the receiver answered {code}")),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// RFC 4231, test case 2.
    #[test]
    fn the_signature_is_hmac_sha256() {
        assert_eq!(
            signature(b"Jefe", b"what do ya want for nothing?"),
            "sha256=5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843"
        );
    }

    /// A render with a stated error tells its bound and confidence; one without tells neither.
    #[test]
    fn a_stated_error_is_told_with_its_bound() {
        let body = |confidence: f64| {
            let info = crate::model::RenderInfo {
                render_id: "7".into(),
                state: crate::model::RenderState::Done,
                error_estimate: 0.06,
                error_bound: if confidence > 0.0 { 0.07 } else { 0.0 },
                confidence,
                ..Default::default()
            };
            let n = notice(crate::model::Ended { url: "https://example.com/".into(), info });
            serde_json::from_str::<serde_json::Value>(&n.body).unwrap()
        };
        let stated = body(0.95);
        assert_eq!((&stated["error_bound"], &stated["confidence"]), (&0.07.into(), &0.95.into()), "{stated}");
        let plain = body(0.0);
        assert!(plain.get("error_bound").is_none() && plain.get("confidence").is_none(), "{plain}");
        assert_eq!(plain["error_estimate"], 0.06);
    }
}
