//! The plain-HTTP side door of the coordinator and the worker: `GET /metrics`, `/healthz` and
//! `/readyz` for Prometheus and for Kubernetes probes. One request per connection, HTTP/1.1,
//! nothing else is needed; the page itself comes from the caller.

use std::sync::Arc;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// One answer: status code (200, 404, 500, 503) and a plain-text body.
pub struct Page {
    pub code: u16,
    pub body: String,
}

impl Page {
    pub fn ok(body: impl Into<String>) -> Self {
        Self { code: 200, body: body.into() }
    }

    pub fn unavailable(body: impl Into<String>) -> Self {
        Self { code: 503, body: body.into() }
    }

    pub fn not_found() -> Self {
        Self { code: 404, body: "try /metrics, /healthz or /readyz\n".into() }
    }
}

/// Most probe connections open at once; each lives at most a few seconds.
pub const MAX_CONNECTIONS: usize = 64;

/// Serves `page(path)` on every connection until the task is dropped. A client that sends
/// nothing for 5 seconds, or junk, is dropped without harm; past [`MAX_CONNECTIONS`] open, a
/// connection is closed at once.
pub async fn serve(listener: tokio::net::TcpListener, page: Arc<dyn Fn(&str) -> Page + Send + Sync>) {
    let mut acceptor = crate::accept::Acceptor::new(listener, "the probe door");
    let places = Arc::new(tokio::sync::Semaphore::new(MAX_CONNECTIONS));
    loop {
        let (mut socket, _) = acceptor.accept().await;
        // Past the limit, a connection is closed at once.
        let Ok(place) = places.clone().try_acquire_owned() else { continue };
        let page = page.clone();
        tokio::spawn(async move {
            let _place = place;
            let mut buf = [0u8; 2048];
            let n = match tokio::time::timeout(std::time::Duration::from_secs(5), socket.read(&mut buf)).await {
                Ok(Ok(n)) => n,
                _ => return,
            };
            let request = String::from_utf8_lossy(&buf[..n]);
            let path = request.split_whitespace().nth(1).unwrap_or("");
            let Page { code, body } = page(path);
            let reason = match code {
                200 => "OK",
                404 => "Not Found",
                503 => "Service Unavailable",
                _ => "Internal Server Error",
            };
            let response = format!(
                "HTTP/1.1 {code} {reason}\r\nContent-Type: text/plain; version=0.0.4\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
                body.len()
            );
            let _ = socket.write_all(response.as_bytes()).await;
        });
    }
}
