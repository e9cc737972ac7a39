//! A connection to a coordinator, shared by the CLI and the worker: a channel to its URL
//! (plain or TLS, [`connect_channel`]) with advice for the TLS failures people meet, the token on
//! every call ([`Auth`]), a deadline on every call and every stream message ([`within`],
//! [`next_within`]), a growing, jittered delay between failed tries ([`Backoff`]), and a look at
//! what answers at an address that does not speak the coordinator's protocol ([`diagnose`]).

use std::time::Duration;
use tokio_stream::StreamExt;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::transport::Channel;
use tonic::{Request, Status};

/// Why a channel could not be opened: a setup mistake that retrying will not fix, or a
/// coordinator that did not answer (not up yet, or gone), which it may.
#[derive(Debug, thiserror::Error)]
pub enum ConnectError {
    #[error("{0}")]
    Setup(String),
    #[error("{0}")]
    Unreachable(String),
}

/// The longest a call that gets one answer waits for it (a lease's long poll waits its own
/// time on top); a stream waits this long for each message.
pub const ANSWER_WITHIN: Duration = Duration::from_secs(60);

/// `call`, or a DEADLINE_EXCEEDED status naming `what` if the coordinator has not answered
/// within `limit`: a coordinator that stops answering must not hang a client or a worker.
pub async fn within<T>(
    limit: Duration,
    what: &str,
    call: impl std::future::Future<Output = Result<T, tonic::Status>>,
) -> Result<T, tonic::Status> {
    tokio::time::timeout(limit, call).await.unwrap_or_else(|_| {
        Err(tonic::Status::deadline_exceeded(format!(
            "the coordinator did not answer {what} within {} s",
            limit.as_secs()
        )))
    })
}

/// The next message of a stream from the coordinator, within [`ANSWER_WITHIN`].
pub async fn next_within<T>(what: &str, stream: &mut tonic::Streaming<T>) -> Result<Option<T>, tonic::Status> {
    within(ANSWER_WITHIN, what, async { stream.next().await.transpose() }).await
}

/// A channel to `url`: plain for `http://`, TLS for `https://` (trusting `ca` when given, the
/// system's roots otherwise). Connecting gives up after 10 s; an open connection whose peer
/// stops answering HTTP/2 pings (20 s apart, 10 s to answer) is closed.
pub async fn connect_channel(url: &str, ca: Option<&std::path::Path>) -> Result<Channel, ConnectError> {
    if !url.starts_with("http://") && !url.starts_with("https://") {
        let address = url.split_once("://").map_or(url, |(_, rest)| rest);
        return Err(ConnectError::Setup(format!(
            "'{url}' is not a coordinator URL: write http://{address} (or https://{address} if the coordinator \
             speaks TLS)"
        )));
    }
    let mut endpoint = Channel::from_shared(url.to_string())
        .map_err(|e| ConnectError::Setup(format!("'{url}' is not a URL: {e}")))?
        .connect_timeout(Duration::from_secs(10))
        .http2_keep_alive_interval(Duration::from_secs(20))
        .keep_alive_timeout(Duration::from_secs(10))
        .keep_alive_while_idle(true);
    if url.starts_with("https://") {
        let mut tls = tonic::transport::ClientTlsConfig::new().with_native_roots();
        if let Some(ca) = ca {
            let pem = std::fs::read(ca)
                .map_err(|e| ConnectError::Setup(format!("reading the CA certificate {}: {e}", ca.display())))?;
            tls = tls.ca_certificate(tonic::transport::Certificate::from_pem(pem));
        }
        endpoint = endpoint.tls_config(tls).map_err(|e| ConnectError::Setup(format!("TLS setup: {e}")))?;
    } else if ca.is_some() {
        return Err(ConnectError::Setup(format!("--ca given but '{url}' is not https://")));
    }
    endpoint.connect().await.map_err(|e| {
        let mut msg = e.to_string();
        let mut source = std::error::Error::source(&e);
        while let Some(s) = source {
            // Layers often repeat their inner error's words ("tcp connect error: tcp connect error").
            let said = s.to_string();
            if !msg.ends_with(&said) {
                msg += &format!(": {said}");
            }
            source = s.source();
        }
        match tls_advice(&msg) {
            Some(advice) => ConnectError::Setup(format!("{advice} ({msg})")),
            None => ConnectError::Unreachable(msg),
        }
    })
}

/// What to do about a TLS failure, from the TLS library's words for it.
fn tls_advice(message: &str) -> Option<&'static str> {
    const ADVICE: [(&str, &str); 6] = [
        (
            "CaUsedAsEndEntity",
            "the coordinator's certificate is a CA certificate (basicConstraints CA:TRUE), which TLS refuses as a \
             server's: give the coordinator a certificate signed by that CA, or make a self-signed one with \
             `-addext basicConstraints=critical,CA:FALSE`",
        ),
        (
            "UnknownIssuer",
            "the coordinator's certificate is not signed by a CA this machine trusts: pass the CA's certificate \
             with --ca (TESSERA_CA)",
        ),
        (
            "NotValidForName",
            "the coordinator's certificate does not name the host in the URL: connect by a name it was issued for, \
             or reissue it with this one in subjectAltName",
        ),
        ("Expired", "the coordinator's certificate has expired: renew it"),
        ("NotValidYet", "the coordinator's certificate is not valid yet: check the clocks of both machines"),
        ("InvalidContentType", "the coordinator does not speak TLS: use http:// instead of https://"),
    ];
    ADVICE.iter().find(|(words, _)| message.contains(words)).map(|(_, advice)| *advice)
}

/// The token, sent as `authorization: Bearer TOKEN` on every call.
#[derive(Clone)]
pub struct Auth(Option<MetadataValue<Ascii>>);

impl Auth {
    pub fn new(token: Option<&str>) -> Self {
        Self(token.and_then(|t| format!("Bearer {t}").parse().ok()))
    }
}

impl tonic::service::Interceptor for Auth {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if let Some(v) = &self.0 {
            request.metadata_mut().insert("authorization", v.clone());
        }
        Ok(request)
    }
}

/// Delays between failed sessions: doubling from 0.2 s to at most 30 s, each with up to 25 %
/// jitter (from the worker's id and the failure count, so that a fleet restarted together does
/// not retry in step).
pub struct Backoff {
    seed: u64,
    pub failures: u32,
}

impl Backoff {
    pub const FIRST: Duration = Duration::from_millis(200);
    pub const MAX: Duration = Duration::from_secs(30);

    pub fn new(worker_id: &str) -> Self {
        // FNV-1a of the id: any spread will do.
        let seed =
            worker_id.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| (h ^ b as u64).wrapping_mul(0x100_0000_01b3));
        Self { seed, failures: 0 }
    }

    pub fn reset(&mut self) {
        self.failures = 0;
    }

    /// The delay before the next try.
    pub fn next_delay(&mut self) -> Duration {
        self.failures = self.failures.saturating_add(1);
        let base = Self::FIRST.saturating_mul(1u32 << (self.failures - 1).min(16)).min(Self::MAX);
        let mixed = (self.seed ^ (self.failures as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15))
            .wrapping_mul(0xBF58_476D_1CE4_E5B9);
        let jitter = (mixed >> 40) as f64 / (1u64 << 24) as f64; // in [0, 1)
        base.mul_f64(1.0 - 0.25 * jitter)
    }
}

/// Says what answers at a coordinator URL that failed, when it is something other than a
/// gRPC coordinator speaking the URL's protocol: it sends the HTTP/2 preface and reads the first
/// bytes back. A TLS server answers with a TLS record, a metrics port with "HTTP/1.1", and a
/// plain coordinator asked for https:// with an HTTP/2 SETTINGS frame.
pub async fn diagnose(url: &str) -> Option<String> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let (tls, rest) = match url.split_once("://") {
        Some(("https", rest)) => (true, rest),
        Some((_, rest)) => (false, rest),
        None => (false, url),
    };
    let authority = rest.split('/').next()?;
    let address = if authority.rsplit_once(':').is_some_and(|(_, p)| p.parse::<u16>().is_ok()) {
        authority.to_string()
    } else {
        format!("{authority}:{}", if tls { 443 } else { 80 })
    };
    let limit = Duration::from_secs(2);
    let mut stream = tokio::time::timeout(limit, tokio::net::TcpStream::connect(&address)).await.ok()?.ok()?;
    tokio::time::timeout(limit, stream.write_all(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n")).await.ok()?.ok()?;
    let mut first = [0u8; 16];
    let n = tokio::time::timeout(limit, stream.read(&mut first)).await.ok()?.ok()?;
    let first = &first[..n];
    let speaks_tls = first.len() >= 2 && (first[0] == 0x15 || first[0] == 0x16) && first[1] == 0x03;
    if speaks_tls && !tls {
        return Some(format!("{address} speaks TLS: use https://{authority}"));
    }
    if first.starts_with(b"HTTP/1.") {
        return Some(format!(
            "{address} answers plain HTTP/1, not gRPC: is it a metrics port, or the dashboard (--http)? Use the \
             coordinator's --listen address"
        ));
    }
    let http2_settings = first.len() >= 4 && first[3] == 0x04;
    if tls && http2_settings {
        return Some(format!("{address} speaks plain HTTP/2 without TLS: use http://{authority}"));
    }
    // HTTP/2 without TLS, as the coordinator speaks it: the dashboard speaks it too, and
    // answers an HTTP/1 request as well, which the coordinator does not.
    if !tls && http2_settings && answers_http1(&address, limit).await {
        return Some(format!(
            "{address} is a web server, not the coordinator's gRPC port: is it the dashboard (--http)? Use the \
             coordinator's --listen address"
        ));
    }
    None
}

/// Whether `address` answers an HTTP/1 request with an HTTP/1 response.
async fn answers_http1(address: &str, limit: Duration) -> bool {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let probe = async {
        let mut stream = tokio::net::TcpStream::connect(address).await.ok()?;
        stream.write_all(b"GET / HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n").await.ok()?;
        let mut first = [0u8; 8];
        let n = stream.read(&mut first).await.ok()?;
        Some(first[..n].starts_with(b"HTTP/1."))
    };
    tokio::time::timeout(limit, probe).await.ok().flatten().unwrap_or(false)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backoff_grows_to_a_cap_with_bounded_jitter() {
        let mut b = Backoff::new("worker-a");
        let delays: Vec<Duration> = (0..12).map(|_| b.next_delay()).collect();
        for (i, d) in delays.iter().enumerate() {
            let base = Backoff::FIRST.saturating_mul(1 << i).min(Backoff::MAX);
            assert!(*d <= base && *d >= base.mul_f64(0.75), "try {i}: {d:?} against {base:?}");
        }
        assert!(delays[11] > Duration::from_secs(22), "capped near 30 s: {:?}", delays[11]);
        b.reset();
        assert!(b.next_delay() <= Backoff::FIRST);
        let other: Vec<Duration> = {
            let mut b = Backoff::new("worker-b");
            (0..12).map(|_| b.next_delay()).collect()
        };
        assert_ne!(delays, other, "two workers retry out of step");
    }
}
