//! The HTTP door: the web dashboard (`dashboard.rs`, its page in `page/`), who may use it
//! (`session.rs`: tokens, the login cookie, CSRF), and the probes and Prometheus metrics
//! (`metrics.rs`). Its connections are bounded as the gRPC door's are (`crate::doors`).

pub mod dashboard;
pub mod metrics;
pub mod notify;
mod session;

pub use dashboard::Dashboard;

use crate::core::CoreError;
use crate::doors::{Guarded, Places, Timers};
use crate::engine::EngineError;
use axum::Json;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde_json::json;
use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

/// Most dashboard connections open at once; more are closed at once.
pub const MAX_CONNECTIONS: usize = 512;
/// How long a connection may take to send a request's headers (and a TLS handshake to finish):
/// one that sends nothing, or a byte at a time, is closed.
pub const HEADER_TIMEOUT: Duration = Duration::from_secs(10);
/// How long an open connection may pass without a byte either way (an event stream sends a
/// keep-alive every 15 s).
const IDLE: Duration = Duration::from_secs(60);

/// A JSON error answer.
fn refuse(code: StatusCode, message: &str) -> Response {
    (code, Json(json!({ "error": message }))).into_response()
}

/// The engine's answer as an HTTP one: its kind decides the code, its message is kept.
fn engine_error(e: EngineError) -> Response {
    let code = match &e {
        EngineError::Core(CoreError::NotFound(_)) => StatusCode::NOT_FOUND,
        EngineError::Core(CoreError::Invalid(_) | CoreError::NotReady(_)) => StatusCode::BAD_REQUEST,
        EngineError::Core(CoreError::Limit(_)) => StatusCode::TOO_MANY_REQUESTS,
        EngineError::Core(CoreError::Refused(_)) => StatusCode::FORBIDDEN,
        _ => StatusCode::INTERNAL_SERVER_ERROR,
    };
    refuse(code, &tessera_request::limits::clip(&e.to_string(), tessera_request::limits::MAX_MESSAGE_BYTES))
}

fn tls_acceptor(cert: &[u8], key: &[u8]) -> std::io::Result<tokio_rustls::TlsAcceptor> {
    use rustls_pki_types::pem::PemObject;
    use rustls_pki_types::{CertificateDer, PrivateKeyDer};
    let bad = |what: &str, e: &dyn std::fmt::Display| std::io::Error::other(format!("the dashboard's TLS {what}: {e}"));
    let chain =
        CertificateDer::pem_slice_iter(cert).collect::<Result<Vec<_>, _>>().map_err(|e| bad("certificate", &e))?;
    let key = PrivateKeyDer::from_pem_slice(key).map_err(|e| bad("key", &e))?;
    let config = tokio_rustls::rustls::ServerConfig::builder_with_provider(Arc::new(
        tokio_rustls::rustls::crypto::ring::default_provider(),
    ))
    .with_safe_default_protocol_versions()
    .map_err(|e| bad("setup", &e))?
    .with_no_client_auth()
    .with_single_cert(chain, key)
    .map_err(|e| bad("certificate and key", &e))?;
    Ok(tokio_rustls::TlsAcceptor::from(Arc::new(config)))
}

/// Serves the dashboard on `listener` until `shutdown` resolves; over TLS with
/// `tls` = (certificate chain, key) in PEM. At most [`MAX_CONNECTIONS`] at once, each sending
/// its headers within [`HEADER_TIMEOUT`] and closed after a minute without a byte either way.
pub async fn serve(
    listener: tokio::net::TcpListener,
    dashboard: Arc<Dashboard>,
    tls: Option<(Vec<u8>, Vec<u8>)>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    serve_limited(listener, dashboard, tls, MAX_CONNECTIONS, HEADER_TIMEOUT, shutdown).await
}

/// [`serve`] with its limits given.
pub async fn serve_limited(
    listener: tokio::net::TcpListener,
    dashboard: Arc<Dashboard>,
    tls: Option<(Vec<u8>, Vec<u8>)>,
    max_connections: usize,
    header_timeout: Duration,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    let app = dashboard.router();
    let acceptor = tls.map(|(cert, key)| tls_acceptor(&cert, &key)).transpose()?;
    let places = Places::new("dashboard", max_connections);
    let timers = Timers { admit_within: header_timeout, admit_on_first_byte: true, idle: Some(IDLE) };
    let mut shutdown = std::pin::pin!(shutdown);
    let mut door = tessera_proto::accept::Acceptor::new(listener, "the dashboard");
    loop {
        let (stream, peer) = tokio::select! {
            accepted = door.accept() => accepted,
            _ = &mut shutdown => return Ok(()),
        };
        let Some(place) = places.take(Some(peer.ip())) else { continue };
        let (acceptor, app) = (acceptor.clone(), app.clone());
        tokio::spawn(async move {
            let stream = Guarded::new(stream, place, timers);
            // The connection's requests vouch for it (see `dashboard::door_checks`).
            let app = tower::Layer::layer(&axum::Extension(stream.admission()), app);
            let service = hyper_util::service::TowerToHyperService::new(app);
            // HTTP/1.1 only: the TLS setup offers no h2, and browsers speak 1.1 over plain HTTP.
            let mut http =
                hyper_util::server::conn::auto::Builder::new(hyper_util::rt::TokioExecutor::new()).http1_only();
            http.http1().timer(hyper_util::rt::TokioTimer::new()).header_read_timeout(header_timeout);
            let _ = match acceptor {
                None => http.serve_connection_with_upgrades(hyper_util::rt::TokioIo::new(stream), service).await,
                Some(acceptor) => {
                    let Ok(Ok(stream)) = tokio::time::timeout(header_timeout, acceptor.accept(stream)).await else {
                        return;
                    };
                    http.serve_connection_with_upgrades(hyper_util::rt::TokioIo::new(stream), service).await
                }
            };
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::http::dashboard::tests::{ALICE, two_users};
    use std::time::Instant;

    /// Over TLS (the coordinator's certificate and key), the dashboard speaks https, and the
    /// login cookie is marked Secure as well as HttpOnly.
    #[tokio::test]
    async fn over_tls_the_login_cookie_is_secure() {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        use tokio_rustls::rustls;
        let key = rcgen::KeyPair::generate().unwrap();
        let cert = rcgen::CertificateParams::new(vec!["localhost".to_string()]).unwrap().self_signed(&key).unwrap();
        let (d, _, _, _dir) = two_users().await;
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let port = listener.local_addr().unwrap().port();
        let tls = Some((cert.pem().into_bytes(), key.serialize_pem().into_bytes()));
        let d = Dashboard::new(d.engine.clone(), d.sessions.tokens.clone(), true);
        tokio::spawn(serve(listener, d, tls, std::future::pending()));

        let mut roots = rustls::RootCertStore::empty();
        roots.add(cert.der().clone()).unwrap();
        let config = rustls::ClientConfig::builder_with_provider(Arc::new(rustls::crypto::ring::default_provider()))
            .with_safe_default_protocol_versions()
            .unwrap()
            .with_root_certificates(roots)
            .with_no_client_auth();
        let connector = tokio_rustls::TlsConnector::from(Arc::new(config));
        let tcp = tokio::net::TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        let name = rustls_pki_types::ServerName::try_from("localhost").unwrap();
        let mut stream = connector.connect(name, tcp).await.expect("the dashboard speaks TLS");
        let body = format!("token={ALICE}");
        let request = format!(
            "POST /login HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\nContent-Type: application/x-www-form-urlencoded\r\nContent-Length: {}\r\n\r\n{body}",
            body.len()
        );
        stream.write_all(request.as_bytes()).await.unwrap();
        let mut answer = Vec::new();
        let _ = stream.read_to_end(&mut answer).await;
        let answer = String::from_utf8_lossy(&answer).to_lowercase();
        assert!(answer.starts_with("http/1.1 303"), "{answer}");
        assert!(answer.contains("; httponly; samesite=strict; secure"), "{answer}");
    }

    /// A connection from 127.0.0.2 (another peer on loopback).
    async fn connect_from_another_peer(port: u16) -> tokio::net::TcpStream {
        let socket = tokio::net::TcpSocket::new_v4().unwrap();
        socket.bind("127.0.0.2:0".parse().unwrap()).unwrap();
        socket.connect(([127, 0, 0, 1], port).into()).await.unwrap()
    }

    /// One peer's silent connections take at most its share of the door's places, so another
    /// peer with a token gets in; an answer to a request without a valid token closes its
    /// connection (no keep-alive), one with a token keeps it open.
    #[tokio::test]
    async fn a_peer_without_a_token_cannot_hold_the_door() {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let (d, _, _, _dir) = two_users().await;
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let port = listener.local_addr().unwrap().port();
        tokio::spawn(serve_limited(listener, d, None, 48, Duration::from_secs(5), std::future::pending()));
        let mut flood = Vec::new();
        for _ in 0..64 {
            flood.push(tokio::net::TcpStream::connect(("127.0.0.1", port)).await.unwrap());
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
        let ask = |path: &str, token: Option<&str>| {
            let auth = token.map_or(String::new(), |t| format!("Authorization: Bearer {t}\r\n"));
            format!("GET {path} HTTP/1.1\r\nHost: localhost\r\n{auth}\r\n")
        };
        // Unauthenticated: answered, then the connection is closed.
        let mut s = connect_from_another_peer(port).await;
        s.write_all(ask("/style.css", None).as_bytes()).await.unwrap();
        let mut answer = Vec::new();
        let closed = tokio::time::timeout(Duration::from_secs(3), s.read_to_end(&mut answer)).await;
        assert!(closed.is_ok(), "an unauthenticated connection was kept alive");
        let answer = String::from_utf8_lossy(&answer).to_lowercase();
        assert!(answer.starts_with("http/1.1 200") && answer.contains("connection: close"), "{answer}");
        // With a token: answered, and the connection stays for the next request.
        let mut s = connect_from_another_peer(port).await;
        s.write_all(ask("/api/renders", Some(ALICE)).as_bytes()).await.unwrap();
        let mut buf = vec![0u8; 1 << 16];
        let n = tokio::time::timeout(Duration::from_secs(3), s.read(&mut buf)).await.unwrap().unwrap();
        let answer = String::from_utf8_lossy(&buf[..n]).to_lowercase();
        assert!(answer.starts_with("http/1.1 200") && !answer.contains("connection: close"), "{answer}");
        assert!(tokio::time::timeout(Duration::from_millis(500), s.read(&mut buf)).await.is_err(), "it was closed");
        drop(flood);
    }

    /// The dashboard's doors are bounded: a connection past the limit is closed at once, and one
    /// that sends no request within the header timeout is closed then.
    #[tokio::test]
    async fn connections_are_limited_and_silent_ones_closed() {
        use tokio::io::AsyncReadExt;
        let (d, _, _, _dir) = two_users().await;
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let port = listener.local_addr().unwrap().port();
        let timeout = Duration::from_millis(300);
        tokio::spawn(serve_limited(listener, d, None, 2, timeout, std::future::pending()));
        let closed_within = |mut s: tokio::net::TcpStream, limit: Duration| async move {
            let mut buf = [0u8; 16];
            matches!(tokio::time::timeout(limit, s.read(&mut buf)).await, Ok(Ok(0) | Err(_)))
        };
        let first = tokio::net::TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        let second = tokio::net::TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        tokio::time::sleep(Duration::from_millis(50)).await;
        let third = tokio::net::TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        assert!(
            closed_within(third, Duration::from_millis(200)).await,
            "a connection past the limit is closed at once"
        );
        let started = Instant::now();
        assert!(closed_within(first, Duration::from_secs(5)).await, "a silent connection is closed");
        assert!(started.elapsed() >= Duration::from_millis(200), "not before its time");
        assert!(closed_within(second, Duration::from_secs(5)).await);
        // With the places free again, a request is answered.
        let mut s = tokio::net::TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        tokio::io::AsyncWriteExt::write_all(
            &mut s,
            b"GET /api/renders HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n",
        )
        .await
        .unwrap();
        let mut answer = String::new();
        s.read_to_string(&mut answer).await.unwrap();
        assert!(answer.starts_with("HTTP/1.1 401"), "{answer}");
    }
}
