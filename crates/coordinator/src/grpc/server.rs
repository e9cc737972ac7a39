//! The gRPC door: both services on one listener, behind the token check and the connection
//! limits of [`crate::doors`].

use super::service::{RenderApi, WorkApi};
use crate::engine::Engine;
use crate::users::{Identity, Role, Users};
use std::future::Future;
use std::sync::atomic::Ordering;
use std::sync::{Arc, RwLock};
use tessera_proto::v1::render_service_server::RenderServiceServer;
use tessera_proto::v1::work_service_server::WorkServiceServer;
use tonic::{Request, Status};

/// Tokens callers must present; `None` accepts anyone (only allowed on loopback by the CLI).
/// `users` (a token file, reloaded on SIGHUP) adds per-user tokens with roles; the shared
/// tokens keep working beside it, with every right.
#[derive(Clone, Debug, Default)]
pub struct Tokens {
    pub clients: Option<String>,
    pub workers: Option<String>,
    pub users: Option<Arc<RwLock<Users>>>,
}

#[derive(Clone)]
struct TokenCheck {
    expected: Option<String>,
    users: Option<Arc<RwLock<Users>>>,
    who: &'static str,
}

impl TokenCheck {
    /// Who an admitted caller is: a per-user token's user, the shared token's holder, or
    /// anyone where there is no token.
    fn identity(&self, user: &Option<Identity>, presented: Option<&str>) -> Identity {
        match (user, &self.expected) {
            (Some(user), _) => user.clone(),
            (None, Some(_)) if presented.is_some() => Identity::shared_token(),
            (None, _) => Identity::anyone(),
        }
    }

    /// The user a per-user token belongs to, if it is one and its role fits this service.
    fn user(&self, presented: Option<&str>) -> Result<Option<Identity>, (Status, Log)> {
        let (Some(users), Some(token)) = (&self.users, presented) else { return Ok(None) };
        let Some(identity) = users.read().ok().and_then(|u| u.identify(token).cloned()) else { return Ok(None) };
        let allowed = match self.who {
            "worker" => matches!(identity.role, Role::Worker | Role::Admin),
            _ => matches!(identity.role, Role::Submit | Role::Admin),
        };
        if !allowed {
            return Err((
                Status::permission_denied(format!(
                    "'{}' has the {:?} role, which may not make {} calls",
                    identity.name, identity.role, self.who
                )),
                Log::Warn(format!(
                    "refused a {} call from '{}', whose role is {:?}",
                    self.who, identity.name, identity.role
                )),
            ));
        }
        Ok(Some(identity))
    }
}

/// What admitted a caller, kept by a stream that lasts (`WatchRender`, the dashboard's events)
/// to ask again as it goes: a user removed from the token file, or given another role, on
/// SIGHUP loses the streams they had open, not only their next call. The shared tokens and a
/// coordinator without tokens do not change while it runs.
#[derive(Clone, Debug)]
pub struct Standing {
    users: Option<Arc<RwLock<Users>>>,
    presented: Option<String>,
    /// The per-user identity the token gave (`None`: the shared token, or no tokens).
    user: Option<Identity>,
}

impl Standing {
    /// Whether the token still admits the same user as when the stream began.
    pub fn holds(&self) -> bool {
        let (Some(user), Some(users)) = (&self.user, &self.users) else { return true };
        let now = users.read().ok().and_then(|u| self.presented.as_deref().and_then(|t| u.identify(t).cloned()));
        now.as_ref() == Some(user)
    }
}

impl tonic::service::Interceptor for TokenCheck {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        let presented = request
            .metadata()
            .get("authorization")
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "))
            .map(str::to_string);
        let user = self.check(presented.as_deref())?;
        crate::doors::admit(&request);
        let identity = self.identity(&user, presented.as_deref());
        let standing = Standing { users: self.users.clone(), presented, user };
        request.extensions_mut().insert(identity);
        request.extensions_mut().insert(standing);
        Ok(request)
    }
}

impl Tokens {
    /// Who a client (the CLI, the dashboard) presenting `presented` is, checked as every gRPC
    /// call of the render service is: a per-user token gives its user, the shared token or a
    /// coordinator without tokens anyone with every right.
    #[allow(clippy::result_large_err)]
    pub fn client(&self, presented: Option<&str>) -> Result<Identity, Status> {
        Ok(self.client_standing(presented)?.0)
    }

    /// [`Tokens::client`], with what admitted the caller, for a long stream to ask again.
    #[allow(clippy::result_large_err)]
    pub fn client_standing(&self, presented: Option<&str>) -> Result<(Identity, Standing), Status> {
        let check = self.client_check();
        let user = check.check(presented)?;
        let who = check.identity(&user, presented);
        let standing = Standing { users: self.users.clone(), presented: presented.map(str::to_string), user };
        Ok((who, standing))
    }

    /// Whether `presented` admits a client, asked without a word in the log.
    pub fn admits_client(&self, presented: Option<&str>) -> bool {
        self.client_check().verdict(presented).is_ok()
    }

    /// The check of the render service's callers (the CLI, the dashboard).
    fn client_check(&self) -> TokenCheck {
        TokenCheck { expected: self.clients.clone(), users: self.users.clone(), who: "client" }
    }

    /// The check of the work service's callers (workers).
    fn worker_check(&self) -> TokenCheck {
        TokenCheck { expected: self.workers.clone(), users: self.users.clone(), who: "worker" }
    }

    /// Whether clients must present a token at all.
    pub fn required(&self) -> bool {
        self.clients.is_some() || self.users.is_some()
    }
}

impl TokenCheck {
    /// Checks `presented`: `Some` the user of a per-user token, `None` for the shared token or
    /// a coordinator without tokens. A refusal is logged.
    #[allow(clippy::result_large_err)]
    fn check(&self, presented: Option<&str>) -> Result<Option<Identity>, Status> {
        self.verdict(presented).map_err(|(status, log)| {
            match log {
                Log::Warn(m) => tracing::warn!("{m}"),
                Log::Error(m) => tracing::error!("{m}"),
            }
            status
        })
    }

    /// [`TokenCheck::check`] without a word in the log (for the dashboard, which asks of every
    /// request whether it comes from someone admitted, the login page's included).
    #[allow(clippy::result_large_err)]
    fn verdict(&self, presented: Option<&str>) -> Result<Option<Identity>, (Status, Log)> {
        let who = self.who;
        if let Some(identity) = self.user(presented)? {
            return Ok(Some(identity));
        }
        let Some(expected) = &self.expected else {
            if self.users.is_some() {
                return Err((
                    Status::unauthenticated(format!("this coordinator requires a {who} token")),
                    Log::Warn(format!("refused a {who} call with an unknown or missing token")),
                ));
            }
            return Ok(None);
        };
        // Fail closed: a token that is empty or too short must never let anyone in, whoever
        // built these `Tokens` (the CLI refuses such tokens before it gets here).
        if let Err(why) = tessera_proto::token::check_token(expected) {
            return Err((
                Status::unauthenticated(format!("the coordinator's {who} token is unusable; refusing every call")),
                Log::Error(format!("refused a {who} call: the coordinator's own {who} token is unusable: {why}")),
            ));
        }
        match presented {
            Some(t) if constant_time_eq(t.as_bytes(), expected.as_bytes()) => Ok(None),
            Some(_) => Err((
                Status::unauthenticated(format!("wrong {who} token")),
                Log::Warn(format!("refused a {who} call with a wrong token")),
            )),
            None => Err((
                Status::unauthenticated(format!("this coordinator requires a {who} token (--token or TESSERA_TOKEN)")),
                Log::Warn(format!("refused a {who} call without a token")),
            )),
        }
    }
}

/// What a refusal writes to the log.
enum Log {
    Warn(String),
    Error(String),
}

pub(crate) fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// Most connections open at once, by default.
pub const MAX_CONNECTIONS: usize = 4096;

/// Connections the kernel holds for the coordinator before it accepts them (clamped to the
/// system's `net.core.somaxconn`). A farm's workers start together: with tokio's 1,024, a
/// thousand connecting at once overflowed the queue while the coordinator was busy, and some
/// were reset after they had sent their first request.
pub const ACCEPT_QUEUE: u32 = 4096;

/// A listener on `addr` for [`serve`], with an accept queue of [`ACCEPT_QUEUE`].
pub fn listen(addr: std::net::SocketAddr) -> std::io::Result<tokio::net::TcpListener> {
    let socket = if addr.is_ipv4() { tokio::net::TcpSocket::new_v4()? } else { tokio::net::TcpSocket::new_v6()? };
    socket.set_reuseaddr(true)?;
    socket.bind(addr)?;
    socket.listen(ACCEPT_QUEUE)
}

/// Serves until `shutdown` resolves; with `tls` = (certificate chain, key) in PEM, over TLS.
/// At most `max_connections` are open at once; one that makes no authenticated request within
/// [`crate::doors::FIRST_REQUEST`] is closed, and so is one whose peer stops answering
/// HTTP/2 pings (20 s apart, 10 s to answer).
pub async fn serve(
    listener: tokio::net::TcpListener,
    engine: Arc<Engine>,
    tokens: Tokens,
    tls: Option<(Vec<u8>, Vec<u8>)>,
    max_connections: usize,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), tonic::transport::Error> {
    use tonic::service::interceptor::InterceptedService;
    let render = InterceptedService::new(
        RenderServiceServer::new(RenderApi::new(engine.clone())).max_decoding_message_size(8 << 20),
        tokens.client_check(),
    );
    let work = InterceptedService::new(
        WorkServiceServer::new(WorkApi::new(engine.clone())).max_decoding_message_size(8 << 20),
        tokens.worker_check(),
    );
    let mut builder = tonic::transport::Server::builder()
        .http2_keepalive_interval(Some(std::time::Duration::from_secs(20)))
        .http2_keepalive_timeout(Some(std::time::Duration::from_secs(10)))
        .max_concurrent_streams(Some(256));
    if let Some((cert, key)) = tls {
        let identity = tonic::transport::Identity::from_pem(cert, key);
        builder = builder.tls_config(tonic::transport::ServerTlsConfig::new().identity(identity))?;
    }
    engine.serving.store(true, Ordering::Relaxed);
    let readiness = engine.clone();
    let shutdown = async move {
        shutdown.await;
        readiness.serving.store(false, Ordering::Relaxed);
    };
    let served = builder
        .add_service(render)
        .add_service(work)
        .serve_with_incoming_shutdown(crate::doors::guarded(listener, max_connections), shutdown)
        .await;
    engine.serving.store(false, Ordering::Relaxed);
    served
}

#[cfg(test)]
mod tests {
    use super::*;
    use tonic::service::Interceptor;

    fn call(expected: Option<&str>, header: Option<&str>) -> Result<(), Status> {
        let mut check = TokenCheck { expected: expected.map(str::to_string), users: None, who: "client" };
        let mut request = Request::new(());
        if let Some(h) = header {
            request.metadata_mut().insert("authorization", h.parse().unwrap());
        }
        check.call(request).map(|_| ())
    }

    #[test]
    fn an_unusable_expected_token_refuses_everyone() {
        const GOOD: &str = "a-good-long-token-0123";
        assert!(call(Some(GOOD), Some(&format!("Bearer {GOOD}"))).is_ok());
        assert!(call(Some(GOOD), Some("Bearer ")).is_err());
        assert!(call(Some(GOOD), None).is_err());
        // Built around the CLI's checks, an empty or short token still lets nobody in.
        assert!(call(Some(""), Some("Bearer ")).is_err(), "an empty token turned auth off");
        assert!(call(Some("x"), Some("Bearer x")).is_err(), "a one-byte token was accepted");
        assert!(call(None, None).is_ok(), "no token configured: loopback-only, open");
    }

    /// A token file whose users include the empty token's hash (refused when the file is read,
    /// but the check at the door must not depend on that): `Bearer ` with nothing after it, or no
    /// token at all, acts as no one, on both services.
    #[test]
    fn an_empty_bearer_token_is_no_user_whatever_the_file_lists() {
        use crate::users::{Identity, Role, Users, token_hash};
        let admin = Identity { name: "eve".into(), role: Role::Admin };
        let users = Users::from_hashes([(token_hash(""), admin)]);
        let users = Some(Arc::new(RwLock::new(users)));
        for who in ["client", "worker"] {
            let mut check = TokenCheck { expected: None, users: users.clone(), who };
            for header in [Some("Bearer "), Some("Bearer"), None] {
                let mut request = Request::new(());
                if let Some(h) = header {
                    request.metadata_mut().insert("authorization", h.parse().unwrap());
                }
                let refused = check.call(request).map(|_| ()).unwrap_err();
                assert_eq!(refused.code(), tonic::Code::Unauthenticated, "{who} {header:?}");
            }
        }
        let tokens = Tokens { clients: None, workers: None, users };
        assert!(tokens.client(Some("")).is_err(), "the dashboard's check (an empty cookie) refuses it too");
    }

    /// The shared token has a name its renders are listed under; no token, no name; a token
    /// file may give that name only to an admin.
    #[test]
    fn the_shared_token_has_a_name() {
        const GOOD: &str = "a-good-long-token-0123";
        let shared = Tokens { clients: Some(GOOD.into()), workers: None, users: None };
        assert_eq!(shared.client(Some(GOOD)).unwrap().name, crate::users::SHARED_TOKEN_NAME);
        let open = Tokens { clients: None, workers: None, users: None };
        assert_eq!(open.client(None).unwrap().name, "");
        // The gRPC door's check names it alike.
        let mut check = TokenCheck { expected: Some(GOOD.into()), users: None, who: "client" };
        let mut request = Request::new(());
        request.metadata_mut().insert("authorization", format!("Bearer {GOOD}").parse().unwrap());
        let admitted = check.call(request).unwrap();
        assert_eq!(admitted.extensions().get::<crate::users::Identity>().unwrap().name, "admin");
        let hash = crate::users::token_hash(GOOD);
        let e = crate::users::Users::parse(&format!("admin submit {hash}")).unwrap_err();
        assert!(e.contains("give this submit user another name"), "{e}");
        assert!(crate::users::Users::parse(&format!("admin admin {hash}")).is_ok());
    }
}
