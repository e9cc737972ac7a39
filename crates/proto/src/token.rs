//! The shared secret callers present as `authorization: Bearer TOKEN`. One rule for every place
//! a token is read (the coordinator's `--token` and `--worker-token`, a worker's and a client's
//! `--token`, the same from the environment): a token is at least [`MIN_TOKEN_BYTES`] bytes that
//! can travel in an HTTP header. An empty one must never mean "no authentication".

/// Shortest token accepted: 16 bytes, 128 bits when random.
pub const MIN_TOKEN_BYTES: usize = 16;

/// Checks a token, saying what is wrong and how to make a good one.
pub fn check_token(token: &str) -> Result<(), String> {
    const HOW: &str = "use a long random one, e.g. the output of `openssl rand -hex 32`";
    if token.is_empty() {
        return Err(format!("the token is empty, which would turn authentication off: {HOW}"));
    }
    if token.len() < MIN_TOKEN_BYTES {
        return Err(format!(
            "the token is {} bytes, under the {MIN_TOKEN_BYTES}-byte minimum (a short token can be guessed): {HOW}",
            token.len()
        ));
    }
    if !token.bytes().all(|b| b.is_ascii_graphic()) {
        return Err(format!(
            "the token holds spaces or characters outside printable ASCII, which a header cannot carry: {HOW}"
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn empty_short_and_unprintable_tokens_are_refused() {
        assert!(check_token("").unwrap_err().contains("empty"));
        assert!(check_token("x").unwrap_err().contains("1 bytes, under the 16-byte minimum"));
        assert!(check_token("fifteen-bytes!!").is_err());
        assert!(check_token("sixteen-bytes!!!").is_ok());
        assert!(check_token("sixteen bytes and a space").unwrap_err().contains("printable ASCII"));
        assert!(check_token("caf\u{e9}-caf\u{e9}-caf\u{e9}-caf\u{e9}").is_err());
    }
}
