//! The `tessera` commands the README and the guides show: every fenced shell block of `README.md`
//! and `docs/*.md`, split as a shell would split it (quotes, comments, `\` continuations,
//! `&&`, `;`, `|` and `&` between commands, `NAME=value` before one), and the commands that run
//! `tessera` kept. The binary's unit tests parse each one with its own argument parser; the docs
//! check runs the quick ones.

use std::path::{Path, PathBuf};

/// One documented command: where it is shown, and its words after `tessera`.
#[derive(Clone, Debug)]
pub struct DocCommand {
    pub file: String,
    pub line: usize,
    pub args: Vec<String>,
}

impl std::fmt::Display for DocCommand {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}:{}: tessera {}", self.file, self.line, self.args.join(" "))
    }
}

/// The repository's root, from a crate's directory.
pub fn repository(manifest_dir: &str) -> PathBuf {
    Path::new(manifest_dir).join("../..")
}

/// The markdown files that document commands: the README and every guide in `docs/`.
pub fn documents(repo: &Path) -> Vec<PathBuf> {
    let mut files = vec![repo.join("README.md")];
    let mut guides: Vec<PathBuf> = std::fs::read_dir(repo.join("docs"))
        .map(|d| d.flatten().map(|e| e.path()).filter(|p| p.extension().is_some_and(|x| x == "md")).collect())
        .unwrap_or_default();
    guides.sort();
    files.extend(guides);
    files
}

/// Every `tessera` command in the fenced `sh` blocks of `repo`'s documents.
pub fn documented_commands(repo: &Path) -> Vec<DocCommand> {
    let mut out = Vec::new();
    for path in documents(repo) {
        let text = std::fs::read_to_string(&path).unwrap_or_default();
        let file = path.strip_prefix(repo).unwrap_or(&path).display().to_string();
        for (line, block) in sh_blocks(&text) {
            for (offset, words) in commands(&block) {
                let first = words.iter().position(|w| !is_assignment(w));
                if let Some(i) = first.filter(|&i| words[i] == "tessera") {
                    out.push(DocCommand { file: file.clone(), line: line + offset, args: words[i + 1..].to_vec() });
                }
            }
        }
    }
    out
}

/// The fenced shell blocks of a markdown text (tagged `sh`, or untagged), each with the line its
/// first command is on.
fn sh_blocks(text: &str) -> Vec<(usize, String)> {
    let mut blocks = Vec::new();
    // Inside a fence: the block being read, or `None` inside a block of another language.
    let mut open: Option<Option<(usize, String)>> = None;
    for (i, line) in text.lines().enumerate() {
        let fence = line.trim_start().strip_prefix("```");
        match (&mut open, fence) {
            (None, Some(tag)) => {
                open = Some(matches!(tag.trim(), "" | "sh" | "bash" | "shell").then(|| (i + 2, String::new())))
            }
            (Some(_), Some(_)) => blocks.extend(open.take().flatten()),
            (Some(Some((_, body))), None) => {
                body.push_str(line);
                body.push('\n');
            }
            _ => {}
        }
    }
    blocks
}

fn is_assignment(word: &str) -> bool {
    word.split_once('=').is_some_and(|(name, _)| {
        !name.is_empty() && name.chars().all(|c| c.is_ascii_uppercase() || c.is_ascii_digit() || c == '_')
    })
}

/// A shell script's simple commands, each with its line (from 0) and words, quotes removed.
fn commands(script: &str) -> Vec<(usize, Vec<String>)> {
    let mut out = Vec::new();
    let (mut words, mut word, mut in_word) = (Vec::new(), String::new(), false);
    let (mut line, mut start) = (0usize, 0usize);
    let mut chars = script.chars().peekable();
    let end_word = |words: &mut Vec<String>, word: &mut String, in_word: &mut bool| {
        if *in_word {
            words.push(std::mem::take(word));
            *in_word = false;
        }
    };
    while let Some(c) = chars.next() {
        match c {
            '\\' if chars.peek() == Some(&'\n') => {
                chars.next();
                line += 1;
            }
            '\'' => {
                in_word = true;
                for q in chars.by_ref() {
                    if q == '\'' {
                        break;
                    }
                    word.push(q);
                }
            }
            '"' => {
                in_word = true;
                while let Some(q) = chars.next() {
                    match q {
                        '"' => break,
                        '\\' => word.extend(chars.next()),
                        _ => word.push(q),
                    }
                }
            }
            '#' if !in_word => {
                for q in chars.by_ref() {
                    if q == '\n' {
                        break;
                    }
                }
                end_word(&mut words, &mut word, &mut in_word);
                if !words.is_empty() {
                    out.push((start, std::mem::take(&mut words)));
                }
                line += 1;
                start = line;
            }
            '\n' | ';' | '&' | '|' => {
                end_word(&mut words, &mut word, &mut in_word);
                if !words.is_empty() {
                    out.push((start, std::mem::take(&mut words)));
                }
                if c == '\n' {
                    line += 1;
                }
                start = line;
            }
            c if c.is_whitespace() => end_word(&mut words, &mut word, &mut in_word),
            c => {
                in_word = true;
                word.push(c);
            }
        }
    }
    end_word(&mut words, &mut word, &mut in_word);
    if !words.is_empty() {
        out.push((start, words));
    }
    out
}

#[test]
fn commands_split_as_a_shell_splits_them() {
    let script = "tessera render walk.glb --frames 1-48 --out shot.####.exr   # a comment\n\
                  TOKEN=x tessera submit 'builtin:furnace?a=1&b=2' \\\n  --spp 4 && tessera status\n\
                  kill %2 %1 && wait\n";
    let cmds = commands(script);
    let words: Vec<Vec<&str>> = cmds.iter().map(|(_, w)| w.iter().map(String::as_str).collect()).collect();
    assert_eq!(
        words,
        [
            vec!["tessera", "render", "walk.glb", "--frames", "1-48", "--out", "shot.####.exr"],
            vec!["TOKEN=x", "tessera", "submit", "builtin:furnace?a=1&b=2", "--spp", "4"],
            vec!["tessera", "status"],
            vec!["kill", "%2", "%1"],
            vec!["wait"],
        ]
    );
    assert_eq!(cmds.iter().map(|(l, _)| *l).collect::<Vec<_>>(), [0, 1, 2, 3, 3]);
}
