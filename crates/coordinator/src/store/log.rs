//! Each render's log, and each sequence's: what happened to it (submitted, jobs that failed
//! and on which worker, pauses and priorities and who set them, retries, blocks, its end),
//! stored so that it outlives restarts. A log keeps its last [`LOG_LINES`] lines; older ones
//! are dropped and counted.

use super::StoreError;
use rusqlite::{Connection, OptionalExtension, params};

/// Lines a log keeps.
pub const LOG_LINES: i64 = 200;

pub(super) const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS render_log (
    id INTEGER PRIMARY KEY,
    render INTEGER NOT NULL,
    sequence INTEGER NOT NULL,
    at REAL NOT NULL,
    line TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS render_log_by_render ON render_log (render, sequence, id);
CREATE TABLE IF NOT EXISTS render_log_dropped (
    render INTEGER NOT NULL,
    sequence INTEGER NOT NULL,
    dropped INTEGER NOT NULL,
    PRIMARY KEY (render, sequence)
);
";

/// Whose log: a render's, or a sequence's (by its first frame's id).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LogOf {
    pub id: i64,
    pub sequence: bool,
}

/// One line of a log: its place (lines come in increasing `id`), when (seconds since the Unix
/// epoch) and what.
#[derive(Clone, Debug, PartialEq)]
pub struct LogLine {
    pub id: i64,
    pub at: f64,
    pub line: String,
}

/// Lines of a log after a place in it, and how many older lines were dropped.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LogPage {
    pub lines: Vec<LogLine>,
    pub dropped: u64,
}

/// Appends a line to `of`'s log, dropping (and counting) the oldest past [`LOG_LINES`].
pub(super) fn append(db: &Connection, of: LogOf, at: f64, line: &str) -> rusqlite::Result<()> {
    db.prepare_cached("INSERT INTO render_log (render, sequence, at, line) VALUES (?1, ?2, ?3, ?4)")?
        .execute(params![of.id, of.sequence, at, line])?;
    let oldest_kept: Option<i64> = db
        .prepare_cached(
            "SELECT id FROM render_log WHERE render = ?1 AND sequence = ?2 ORDER BY id DESC LIMIT 1 OFFSET ?3",
        )?
        .query_row(params![of.id, of.sequence, LOG_LINES - 1], |r| r.get(0))
        .optional()?;
    if let Some(oldest) = oldest_kept {
        let dropped = db
            .prepare_cached("DELETE FROM render_log WHERE render = ?1 AND sequence = ?2 AND id < ?3")?
            .execute(params![of.id, of.sequence, oldest])?;
        if dropped > 0 {
            db.prepare_cached(
                "INSERT INTO render_log_dropped (render, sequence, dropped) VALUES (?1, ?2, ?3)
                 ON CONFLICT (render, sequence) DO UPDATE SET dropped = dropped + ?3",
            )?
            .execute(params![of.id, of.sequence, dropped as i64])?;
        }
    }
    Ok(())
}

/// The lines of `of`'s log after line `after` (0: from the first kept), at most `limit`.
pub(super) fn read(db: &Connection, of: LogOf, after: i64, limit: i64) -> Result<LogPage, StoreError> {
    let mut stmt = db.prepare_cached(
        "SELECT id, at, line FROM render_log WHERE render = ?1 AND sequence = ?2 AND id > ?3 ORDER BY id LIMIT ?4",
    )?;
    let lines = stmt
        .query_map(params![of.id, of.sequence, after, limit], |r| {
            Ok(LogLine { id: r.get(0)?, at: r.get(1)?, line: r.get(2)? })
        })?
        .collect::<Result<Vec<_>, _>>()?;
    let dropped: Option<i64> = db
        .query_row(
            "SELECT dropped FROM render_log_dropped WHERE render = ?1 AND sequence = ?2",
            params![of.id, of.sequence],
            |r| r.get(0),
        )
        .optional()?;
    Ok(LogPage { lines, dropped: dropped.unwrap_or(0) as u64 })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A log keeps its last [`LOG_LINES`] lines and counts the ones it dropped; another render's
    /// log, or the sequence's of the same id, is its own.
    #[test]
    fn a_log_keeps_its_last_lines_and_counts_the_rest() {
        let db = Connection::open_in_memory().unwrap();
        db.execute_batch(SCHEMA).unwrap();
        let (render, sequence, other) =
            (LogOf { id: 1, sequence: false }, LogOf { id: 1, sequence: true }, LogOf { id: 2, sequence: false });
        for i in 0..LOG_LINES + 50 {
            append(&db, render, i as f64, &format!("line {i}")).unwrap();
        }
        append(&db, sequence, 0.0, "the sequence's").unwrap();
        append(&db, other, 0.0, "another's").unwrap();
        let page = read(&db, render, 0, 1000).unwrap();
        assert_eq!((page.lines.len() as i64, page.dropped), (LOG_LINES, 50));
        assert_eq!(page.lines[0].line, "line 50");
        assert_eq!(page.lines.last().unwrap().line, format!("line {}", LOG_LINES + 49));
        let after = page.lines[LOG_LINES as usize - 3].id;
        assert_eq!(read(&db, render, after, 1000).unwrap().lines.len(), 2, "the lines after one");
        assert_eq!(read(&db, sequence, 0, 10).unwrap().lines[0].line, "the sequence's");
        let others = read(&db, other, 0, 10).unwrap();
        assert_eq!((others.lines.len(), others.dropped), (1, 0));
    }
}
