//! The coordinator's HTTP side door: `GET /metrics` (Prometheus text format), `/healthz` (the
//! process answers and its state is sound, without waiting for the state lock) and `/readyz` (it is serving gRPC: false before the
//! listener is up and once shutdown has begun, so a load balancer stops sending clients).

use crate::service::Shared;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use tessera_proto::probe::{self, Page};

pub async fn serve(listener: tokio::net::TcpListener, shared: Arc<Shared>) {
    probe::serve(listener, Arc::new(move |path: &str| page(&shared, path))).await
}

fn page(shared: &Shared, path: &str) -> Page {
    match path {
        "/metrics" => match shared.with(|c| Ok(c.prometheus())) {
            Ok(text) => Page::ok(text),
            Err(e) => Page { code: 500, body: e.message().to_string() },
        },
        "/healthz" => match shared.healthy() {
            Ok(()) => Page::ok("ok\n"),
            Err(e) => Page { code: 500, body: format!("{e}\n") },
        },
        "/readyz" if shared.serving.load(Ordering::Relaxed) => Page::ok("ready\n"),
        "/readyz" => Page::unavailable("not serving (starting or shutting down)\n"),
        _ => Page::not_found(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Core, CoreConfig};

    #[test]
    fn healthz_answers_while_the_core_is_busy() {
        let dir = tempfile::Builder::new().prefix("tessera-healthz-").tempdir().unwrap();
        let shared = Shared::new(Core::open(CoreConfig::new(dir.path().to_path_buf())).unwrap()).unwrap();
        let (locked_tx, locked_rx) = std::sync::mpsc::channel();
        let (release_tx, release_rx) = std::sync::mpsc::channel::<()>();
        let busy = shared.clone();
        let holder = std::thread::spawn(move || {
            busy.with(|_| {
                locked_tx.send(()).unwrap();
                release_rx.recv().unwrap();
                Ok(())
            })
        });
        locked_rx.recv().unwrap();
        // The lock is held until we say so: a /healthz that waited on it would never return.
        let (tx, rx) = std::sync::mpsc::channel();
        let probe = shared.clone();
        std::thread::spawn(move || tx.send(page(&probe, "/healthz").code).unwrap());
        let code = rx.recv_timeout(std::time::Duration::from_secs(10));
        release_tx.send(()).unwrap();
        holder.join().unwrap().unwrap();
        assert_eq!(code, Ok(200), "/healthz waited on the core lock");
    }
}
