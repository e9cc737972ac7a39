//! Who is asking the HTTP door: the token a request presents (the login cookie, which scripts
//! cannot read, or an `Authorization: Bearer` header) checked as every gRPC call is; the CSRF
//! token a state-changing request must carry (derived from the login token with a key this
//! process made at start, so a form or image on another site cannot act); and the login page.

// Checks fail with the response to send; boxing it would buy nothing per request.
#![allow(clippy::result_large_err)]

use super::dashboard::Dashboard;
use super::refuse;
use crate::grpc::server::{Standing, Tokens, constant_time_eq};
use crate::users::Identity;
use axum::Json;
use axum::extract::{Form, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{Html, IntoResponse, Redirect, Response};
use serde::Deserialize;
use serde_json::json;
use std::sync::Arc;

const LOGIN: &str = include_str!("page/login.html");
const APP: &str = include_str!("page/index.html");
const SCRIPT: &str = include_str!("page/app.js");
const STYLE: &str = include_str!("page/style.css");

/// The cookie that carries the login token (hex-encoded).
pub const COOKIE: &str = "tessera_token";
/// The header state-changing requests carry the session's CSRF token in.
const CSRF_HEADER: &str = "x-tessera-csrf";

/// The HTTP door's sessions: the coordinator's tokens and this process's CSRF key.
pub struct Sessions {
    pub tokens: Tokens,
    /// Whether the door speaks TLS (the login cookie is then `Secure`).
    pub tls: bool,
    /// Keys the CSRF tokens; made at start, so a restart ends every page's session.
    secret: [u8; 32],
    /// The host names the dashboard answers to besides IP addresses and `localhost`.
    hosts: Vec<String>,
}

impl Sessions {
    pub fn new(tokens: Tokens, tls: bool, hosts: Vec<String>) -> Self {
        Self { tokens, tls, secret: process_secret(), hosts }
    }

    /// The token a request presents: the login cookie, or an `Authorization: Bearer` header.
    pub fn presented(headers: &HeaderMap) -> Option<String> {
        if let Some(bearer) =
            headers.get(header::AUTHORIZATION).and_then(|v| v.to_str().ok()).and_then(|v| v.strip_prefix("Bearer "))
        {
            return Some(bearer.to_string());
        }
        let cookies = headers.get_all(header::COOKIE).iter().filter_map(|v| v.to_str().ok());
        cookies
            .flat_map(|line| line.split(';'))
            .filter_map(|c| c.trim().strip_prefix(COOKIE)?.strip_prefix('='))
            .find_map(unhex)
    }

    /// Who is asking, or the answer for someone who may not.
    pub fn who(&self, headers: &HeaderMap) -> Result<(Identity, String), Response> {
        let (identity, _) = self.standing(headers)?;
        Ok((identity, Self::presented(headers).unwrap_or_default()))
    }

    /// Who is asking, and what admitted them (for a stream that lasts to ask again).
    pub fn standing(&self, headers: &HeaderMap) -> Result<(Identity, Standing), Response> {
        self.tokens
            .client_standing(Self::presented(headers).as_deref())
            .map_err(|status| (StatusCode::UNAUTHORIZED, Json(json!({"error": status.message()}))).into_response())
    }

    /// The CSRF token of a session logged in with `token`.
    pub fn csrf(&self, token: &str) -> String {
        blake3::keyed_hash(&self.secret, token.as_bytes()).to_hex().to_string()
    }

    /// Who is asking to change something: a valid token, this session's CSRF header, and no
    /// foreign `Origin`.
    pub fn who_may_act(&self, headers: &HeaderMap) -> Result<Identity, Response> {
        let (who, token) = self.who(headers)?;
        let sent = headers.get(CSRF_HEADER).and_then(|v| v.to_str().ok()).unwrap_or("");
        if !constant_time_eq(sent.as_bytes(), self.csrf(&token).as_bytes()) {
            return Err(refuse(StatusCode::FORBIDDEN, "this request lacks the page's CSRF token: reload the page"));
        }
        self.same_origin(headers)?;
        Ok(who)
    }
}

/// 32 bytes no one else knows: the kernel's randomness, or failing that the clock and process.
fn process_secret() -> [u8; 32] {
    use std::io::Read;
    let mut key = [0u8; 32];
    let read = std::fs::File::open("/dev/urandom").and_then(|mut f| f.read_exact(&mut key));
    if read.is_ok() {
        return key;
    }
    let seed = format!("{:?} {}", std::time::SystemTime::now(), std::process::id());
    *blake3::hash(seed.as_bytes()).as_bytes()
}

impl Sessions {
    /// Refuses a request whose `Origin` is not this dashboard's own: the scheme it serves and
    /// the host the request names (already checked by [`Sessions::check_host`]). `Origin: null`
    /// (a sandboxed frame, a file) is foreign too.
    pub fn same_origin(&self, headers: &HeaderMap) -> Result<(), Response> {
        let Some(origin) = headers.get(header::ORIGIN) else { return Ok(()) };
        let host = headers.get(header::HOST).and_then(|v| v.to_str().ok()).unwrap_or("");
        let scheme = if self.tls { "https" } else { "http" };
        if origin.to_str().ok().is_some_and(|o| o.eq_ignore_ascii_case(&format!("{scheme}://{host}"))) {
            return Ok(());
        }
        let shown = tessera_request::printable(&String::from_utf8_lossy(origin.as_bytes()));
        Err(refuse(StatusCode::FORBIDDEN, &format!("a request from {shown} may not act on this dashboard")))
    }

    /// Refuses a request that names this dashboard by a name it does not answer to. A page on
    /// another site can point its own name at this machine (DNS rebinding) and then read a
    /// tokenless loopback dashboard as its own origin; such a request names that site in
    /// `Host`. Answered to: IP addresses (the bound one included), `localhost`, and the names
    /// given with `--http-host`. A request without `Host` comes from no browser and passes.
    pub fn check_host(&self, headers: &HeaderMap) -> Result<(), Response> {
        let Some(host) = headers.get(header::HOST) else { return Ok(()) };
        let name = host.to_str().ok().map(host_name).unwrap_or_default();
        let named = name.parse::<std::net::IpAddr>().is_ok()
            || name.eq_ignore_ascii_case("localhost")
            || self.hosts.iter().any(|h| h.eq_ignore_ascii_case(name));
        if named {
            return Ok(());
        }
        let shown = tessera_request::printable(&String::from_utf8_lossy(host.as_bytes()));
        tracing::warn!("the dashboard refused a request for the host name '{shown}'");
        Err(refuse(
            StatusCode::MISDIRECTED_REQUEST,
            &format!(
                "this dashboard does not answer to the name '{shown}': open it by IP address or as localhost, or \
                 start the coordinator with --http-host NAME for each name it is reached by"
            ),
        ))
    }
}

/// The host name of a `Host` header: without its port, an IPv6 address without its brackets,
/// and without a final dot.
fn host_name(host: &str) -> &str {
    let name = match host.strip_prefix('[') {
        Some(v6) => v6.split(']').next().unwrap_or(""),
        None => match host.rsplit_once(':') {
            Some((name, port)) if port.bytes().all(|b| b.is_ascii_digit()) => name,
            _ => host,
        },
    };
    name.strip_suffix('.').unwrap_or(name)
}

pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn unhex(s: &str) -> Option<String> {
    if !s.len().is_multiple_of(2) || s.len() > 1024 {
        return None;
    }
    let bytes: Option<Vec<u8>> =
        (0..s.len()).step_by(2).map(|i| u8::from_str_radix(s.get(i..i + 2)?, 16).ok()).collect();
    String::from_utf8(bytes?).ok()
}

fn page(body: &'static str) -> Response {
    let mut r = Html(body).into_response();
    let h = r.headers_mut();
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    h.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(
            "default-src 'self'; img-src 'self' blob: data:; style-src 'self'; frame-ancestors 'none'",
        ),
    );
    r
}

pub async fn index(State(d): State<Arc<Dashboard>>, headers: HeaderMap) -> Response {
    match d.sessions.who(&headers) {
        Ok(_) => page(APP),
        Err(_) => page(LOGIN),
    }
}

pub async fn script(State(d): State<Arc<Dashboard>>, headers: HeaderMap) -> Response {
    if let Err(r) = d.sessions.who(&headers) {
        return r;
    }
    ([(header::CONTENT_TYPE, "text/javascript; charset=utf-8")], SCRIPT).into_response()
}

pub async fn style() -> Response {
    ([(header::CONTENT_TYPE, "text/css; charset=utf-8")], STYLE).into_response()
}

#[derive(Deserialize)]
pub struct LoginForm {
    token: String,
}

pub async fn login(State(d): State<Arc<Dashboard>>, headers: HeaderMap, Form(form): Form<LoginForm>) -> Response {
    if let Err(r) = d.sessions.same_origin(&headers) {
        return r;
    }
    if form.token.is_empty() || d.sessions.tokens.client(Some(&form.token)).is_err() || !d.sessions.tokens.required() {
        tracing::warn!("the dashboard refused a login");
        let page = LOGIN.replace("<p id=\"refused\" hidden>", "<p id=\"refused\">");
        return (StatusCode::UNAUTHORIZED, Html(page)).into_response();
    }
    let secure = if d.sessions.tls { "; Secure" } else { "" };
    let cookie = format!("{COOKIE}={}; Path=/; HttpOnly; SameSite=Strict{secure}", hex(form.token.as_bytes()));
    let mut r = Redirect::to("/").into_response();
    *r.status_mut() = StatusCode::SEE_OTHER;
    r.headers_mut().insert(header::SET_COOKIE, HeaderValue::from_str(&cookie).expect("hex is a valid header"));
    r
}

pub async fn logout(State(d): State<Arc<Dashboard>>, headers: HeaderMap) -> Response {
    if let Err(r) = d.sessions.who_may_act(&headers) {
        return r;
    }
    let mut r = StatusCode::NO_CONTENT.into_response();
    r.headers_mut().insert(
        header::SET_COOKIE,
        HeaderValue::from_static("tessera_token=; Path=/; HttpOnly; SameSite=Strict; Max-Age=0"),
    );
    r
}

pub async fn session(State(d): State<Arc<Dashboard>>, headers: HeaderMap) -> Response {
    match d.sessions.who(&headers) {
        Ok((who, token)) => Json(json!({
            "user": who.name,
            "role": format!("{:?}", who.role).to_lowercase(),
            "csrf": d.sessions.csrf(&token),
            "login": d.sessions.tokens.required(),
        }))
        .into_response(),
        Err(r) => r,
    }
}
