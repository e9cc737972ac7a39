//! Tokens on the command line: checked as every token is (`tessera_proto::token::check_token`),
//! and never echoed. clap's own error for a refused value repeats the value, which would put a
//! secret (say, one refused for a trailing newline) into a terminal's scrollback or a service's
//! journal; this parser's error names the flag and what is wrong, not the value.

use clap::builder::TypedValueParser;
use clap::error::{Error, ErrorKind};

/// The value parser of every token flag.
#[derive(Clone, Copy, Debug)]
pub struct Token;

impl TypedValueParser for Token {
    type Value = String;

    fn parse_ref(
        &self,
        cmd: &clap::Command,
        arg: Option<&clap::Arg>,
        value: &std::ffi::OsStr,
    ) -> Result<String, Error> {
        let flag = arg.and_then(|a| a.get_long()).map_or("the token".to_string(), |l| format!("--{l}"));
        let refuse = |why: String| Error::raw(ErrorKind::ValueValidation, format!("{flag}: {why}\n")).with_cmd(cmd);
        let token = value.to_str().ok_or_else(|| refuse("the token is not valid UTF-8".into()))?;
        tessera_proto::token::check_token(token).map_err(refuse)?;
        Ok(token.to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser, Debug)]
    struct Cli {
        #[arg(long, value_parser = Token)]
        token: Option<String>,
    }

    /// A refused token's error says what is wrong and names the flag, never the token.
    #[test]
    fn a_refused_token_is_not_echoed() {
        let secret = "s3cret-but-too-short\n";
        let e = Cli::try_parse_from(["t", "--token", secret]).unwrap_err().to_string();
        assert!(e.contains("--token") && e.contains("printable ASCII"), "{e}");
        assert!(!e.contains("s3cret"), "the error echoes the token: {e}");
        let e = Cli::try_parse_from(["t", "--token", "abc"]).unwrap_err().to_string();
        assert!(e.contains("16-byte minimum") && !e.contains("abc"), "{e}");
        assert_eq!(Cli::try_parse_from(["t", "--token", "a-long-enough-token-0123"]).unwrap().token.unwrap().len(), 24);
    }
}
