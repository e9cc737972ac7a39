//! The coordinator's durable state in SQLite: scenes by BLAKE3 hash, renders, and every accepted
//! job result (its tile sums, exactly encoded). A result is committed before it is acknowledged
//! (ARCHITECTURE.md invariant 5); after a restart, the merged passes and the film are rebuilt from these
//! rows, so nothing acknowledged is rendered again. Every result carries a BLAKE3 checksum of
//! its key and sums; one that fails it is dropped and its passes rendered again, never merged.

mod log;
mod writer;

pub use log::{LOG_LINES, LogLine, LogOf, LogPage};
pub use writer::{WRITER_THREAD, Writer};

use rusqlite::{Connection, OptionalExtension, params};
use std::path::Path;
use tessera_film::Film;
use tessera_proto::sums::decode_tile_sums;

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("database: {0}")]
    Sql(#[from] rusqlite::Error),
    #[error("stored result of render {render} is corrupt: {message}")]
    Corrupt { render: i64, message: String },
    #[error("render {0} does not exist")]
    NoSuchRender(i64),
    #[error("{0}")]
    Unusable(String),
}

/// A render as stored: what to render and how far it got.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredRender {
    pub id: i64,
    pub scene_hash: String,
    pub scene_name: String,
    /// The prost-encoded `tessera.v1.RenderSettings`.
    pub settings: Vec<u8>,
    pub spp: u32,
    pub tile_size: u32,
    pub pass_spp: u32,
    pub priority: i32,
    pub state: String,
    /// Adaptive sampling: relative error to reach per tile (0: off), starting from `min_spp`;
    /// `spp` is then the most a tile may get.
    pub target_error: f64,
    pub min_spp: u32,
    /// Why a failed render failed (empty otherwise).
    pub message: String,
    /// The user who submitted it (empty without per-user tokens).
    pub owner: String,
    /// A frame of a sequence: the id of the sequence's first frame (0: not a frame).
    pub sequence: i64,
    /// When it was submitted, first given to a worker, and ended (done, cancelled or failed),
    /// in seconds since the Unix epoch; 0: not yet (or before these were kept).
    pub submitted_at: f64,
    pub started_at: f64,
    pub ended_at: f64,
    /// The name it was submitted with (`submit --name`; empty: none).
    pub name: String,
    /// Paused (`tessera pause`): it gets no new jobs until resumed. A sequence's frames are
    /// paused together.
    pub paused: bool,
    /// Only workers of this pool take it (empty: any), and what their tags must have
    /// (requirements as `submit --require` writes them, separated by spaces).
    pub pool: String,
    pub requires: String,
    /// Where to POST an event when it (or its sequence) ends (empty: nowhere).
    pub notify: String,
    /// Its sequence's previews first: every n-th frame to this many samples before the rest
    /// (0: none).
    pub preview_every: u32,
    pub preview_spp: u32,
    /// Or the relative error its preview frames stop at (0: by samples).
    pub preview_target: f64,
    /// A finished render's relative error, and the bound it stated on it (`--confidence`; 0:
    /// none), as its image states them (0 and 0: not finished, or finished before they were
    /// kept).
    pub final_error: [f64; 2],
}

/// One accepted job result: passes `first .. first + count` of `tile`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StoredResult {
    pub tile: u32,
    pub first: u32,
    pub count: u32,
}

/// A stored result still to be checked by a second worker (`--verify`): who returned it and
/// the digest of its sums ([`tessera_proto::sums::digest`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Unchecked {
    pub result: StoredResult,
    pub worker: String,
    pub digest: [u8; 32],
}

/// A change to the store. The service's [`Writer`] makes them on its own thread, in the order
/// they were queued, many to a transaction; [`Store::apply`] makes one at once.
#[derive(Debug)]
pub enum Write {
    /// An accepted job result (its sums as `encode_tile_sums` wrote them), returned by
    /// `worker`; `unchecked` while a second worker is still to check it. A blocked worker's
    /// result is not stored (its block may have been committed after the result was accepted).
    Result { render: i64, result: StoredResult, sums: Vec<u8>, worker: String, unchecked: bool },
    /// A result a second worker agreed with.
    Checked { render: i64, tile: u32, first: u32 },
    /// Blocks `worker` for the whole farm (its results disagreed with two other workers'),
    /// saying `why`, and deletes every result it returned.
    Block { worker: String, why: String },
    /// New renders, with the ids (and sequences) the core gave them.
    Renders(Vec<StoredRender>),
    /// A render's state, and why (a failed render's message; empty otherwise).
    State { render: i64, state: &'static str, message: String },
    /// A finished render refined (`tessera refine`): its new samples per pixel and target error.
    Quality { render: i64, spp: u32, target_error: f64 },
    /// A finished render's relative error and its stated bound ([`StoredRender::final_error`]).
    FinalError { render: i64, error: [f64; 2] },
    /// When a render stopped running (done, cancelled or failed), in seconds since the Unix
    /// epoch; 0 when it runs again (a retry).
    Ended { render: i64, at: f64 },
    /// A render's first job went to a worker at `at` (seconds since the Unix epoch).
    Started { render: i64, at: f64 },
    /// A line of a render's or a sequence's log, at `at` (seconds since the Unix epoch).
    Log { of: LogOf, at: f64, line: String },
    /// A render's priority and whether it is paused, or every frame's of the sequence whose
    /// first frame is `target`.
    Steer { target: i64, priority: i32, paused: bool },
    /// A scene (or, if it is there, marks it as stored now), uploaded by `owner` (empty: the
    /// shared token, or no tokens).
    Scene { hash: String, bytes: Vec<u8>, owner: String },
    /// Marks a stored scene as stored now, so that it outlives the collection's grace period.
    TouchScene(String),
    /// Deletes a stored scene whose bytes no longer match their hash (the next submit uploads it
    /// again).
    DeleteScene(String),
    /// Deletes the scenes no running or failed render needs, stored over `grace_seconds` ago.
    CollectScenes { grace_seconds: i64 },
}

/// Makes `w` on `db` (inside whatever transaction `db` is in).
fn apply(db: &Connection, w: &Write) -> rusqlite::Result<()> {
    match w {
        Write::Result { render, result, sums, worker, unchecked } => {
            insert_result(db, *render, result, sums, worker, *unchecked)
        }
        Write::Checked { render, tile, first } => {
            db.execute(
                "UPDATE results SET unchecked = 0 WHERE render = ?1 AND tile = ?2 AND first_pass = ?3",
                params![render, tile, first],
            )?;
            Ok(())
        }
        Write::Block { worker, why } => {
            db.execute(
                "INSERT OR IGNORE INTO blocked_workers (worker, why, blocked_at) VALUES (?1, ?2, ?3)",
                params![worker, why, unix_now()],
            )?;
            db.execute("DELETE FROM results WHERE worker = ?1", [worker])?;
            Ok(())
        }
        Write::Renders(renders) => {
            let mut insert = db.prepare_cached(
                "INSERT INTO renders (id, scene_hash, scene_name, settings, spp, tile_size, pass_spp, priority, state, target_error, min_spp, owner, sequence, message, submitted_at, name, paused, pool, requires, notify, preview_every, preview_spp, preview_target)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16, ?17, ?18, ?19, ?20, ?21, ?22, ?23)",
            )?;
            for r in renders {
                insert.execute(params![
                    r.id,
                    r.scene_hash,
                    r.scene_name,
                    r.settings,
                    r.spp,
                    r.tile_size,
                    r.pass_spp,
                    r.priority,
                    r.state,
                    r.target_error,
                    r.min_spp,
                    r.owner,
                    r.sequence,
                    r.message,
                    r.submitted_at,
                    r.name,
                    r.paused,
                    r.pool,
                    r.requires,
                    r.notify,
                    r.preview_every,
                    r.preview_spp,
                    r.preview_target
                ])?;
            }
            Ok(())
        }
        Write::Log { of, at, line } => log::append(db, *of, *at, line),
        Write::Steer { target, priority, paused } => {
            db.execute(
                "UPDATE renders SET priority = ?2, paused = ?3 WHERE id = ?1 OR sequence = ?1",
                params![target, priority, paused],
            )?;
            Ok(())
        }
        Write::State { render, state, message } => {
            let n = db.execute(
                "UPDATE renders SET state = ?2, message = ?3 WHERE id = ?1",
                params![render, state, message],
            )?;
            if n == 0 {
                return Err(rusqlite::Error::QueryReturnedNoRows);
            }
            Ok(())
        }
        Write::Quality { render, spp, target_error } => {
            let n = db.execute(
                "UPDATE renders SET spp = ?2, target_error = ?3 WHERE id = ?1",
                params![render, spp, target_error],
            )?;
            if n == 0 {
                return Err(rusqlite::Error::QueryReturnedNoRows);
            }
            Ok(())
        }
        Write::FinalError { render, error } => {
            // SQLite keeps no NaN (it writes NULL) nor, through every driver, infinities.
            let [estimate, bound] = error.map(|v| if v.is_nan() { 0.0 } else { v.clamp(-f64::MAX, f64::MAX) });
            let sql = "UPDATE renders SET final_error = ?2, final_error_bound = ?3 WHERE id = ?1";
            db.execute(sql, params![render, estimate, bound])?;
            Ok(())
        }
        Write::Ended { render, at } => {
            db.execute("UPDATE renders SET ended_at = ?2 WHERE id = ?1", params![render, at])?;
            Ok(())
        }
        Write::Started { render, at } => {
            db.execute("UPDATE renders SET started_at = ?2 WHERE id = ?1 AND started_at = 0", params![render, at])?;
            Ok(())
        }
        Write::Scene { hash, bytes, owner } => {
            db.execute(
                "INSERT INTO scenes (hash, bytes, stored_at) VALUES (?1, ?2, ?3)
                 ON CONFLICT (hash) DO UPDATE SET bytes = excluded.bytes, stored_at = excluded.stored_at",
                params![hash, bytes, unix_now()],
            )?;
            db.execute("INSERT OR IGNORE INTO scene_uploads (hash, owner) VALUES (?1, ?2)", params![hash, owner])?;
            Ok(())
        }
        Write::TouchScene(hash) => {
            db.execute("UPDATE scenes SET stored_at = ?2 WHERE hash = ?1", params![hash, unix_now()])?;
            Ok(())
        }
        Write::DeleteScene(hash) => {
            db.execute("DELETE FROM scenes WHERE hash = ?1", [hash])?;
            db.execute("DELETE FROM scene_uploads WHERE hash = ?1", [hash])?;
            Ok(())
        }
        Write::CollectScenes { grace_seconds } => {
            let n = db.execute(
                "DELETE FROM scenes WHERE stored_at < ?1
                 AND hash NOT IN (SELECT scene_hash FROM renders WHERE state IN ('running', 'failed'))",
                [unix_now() - grace_seconds],
            )?;
            if n > 0 {
                db.execute("DELETE FROM scene_uploads WHERE hash NOT IN (SELECT hash FROM scenes)", [])?;
                tracing::info!("deleted {n} stored scene(s) that no running or failed render uses");
            }
            Ok(())
        }
    }
}

pub struct Store {
    db: Connection,
}

const SCHEMA: &str = "
PRAGMA journal_mode = WAL;
CREATE TABLE IF NOT EXISTS scenes (
    hash TEXT PRIMARY KEY,
    bytes BLOB NOT NULL
);
CREATE TABLE IF NOT EXISTS renders (
    id INTEGER PRIMARY KEY,
    scene_hash TEXT NOT NULL REFERENCES scenes(hash),
    scene_name TEXT NOT NULL,
    settings BLOB NOT NULL,
    spp INTEGER NOT NULL,
    tile_size INTEGER NOT NULL,
    pass_spp INTEGER NOT NULL,
    priority INTEGER NOT NULL,
    state TEXT NOT NULL,
    target_error REAL NOT NULL,
    min_spp INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS scene_uploads (
    hash TEXT NOT NULL,
    owner TEXT NOT NULL,
    PRIMARY KEY (hash, owner)
);
CREATE TABLE IF NOT EXISTS results (
    render INTEGER NOT NULL REFERENCES renders(id),
    tile INTEGER NOT NULL,
    first_pass INTEGER NOT NULL,
    pass_count INTEGER NOT NULL,
    sums BLOB NOT NULL,
    checksum BLOB,
    PRIMARY KEY (render, tile, first_pass)
);
CREATE TABLE IF NOT EXISTS blocked_workers (
    worker TEXT PRIMARY KEY,
    why TEXT NOT NULL,
    blocked_at INTEGER NOT NULL
);
";

/// Columns added since the first schema, added to older databases when they are opened.
const ADDED_COLUMNS: &[(&str, &str, &str)] = &[
    ("results", "checksum", "BLOB"),
    ("renders", "message", "TEXT NOT NULL DEFAULT ''"),
    ("renders", "owner", "TEXT NOT NULL DEFAULT ''"),
    ("scenes", "stored_at", "INTEGER NOT NULL DEFAULT 0"),
    ("renders", "sequence", "INTEGER NOT NULL DEFAULT 0"),
    ("results", "worker", "TEXT NOT NULL DEFAULT ''"),
    ("results", "unchecked", "INTEGER NOT NULL DEFAULT 0"),
    ("renders", "submitted_at", "REAL NOT NULL DEFAULT 0"),
    ("renders", "started_at", "REAL NOT NULL DEFAULT 0"),
    ("renders", "ended_at", "REAL NOT NULL DEFAULT 0"),
    ("renders", "name", "TEXT NOT NULL DEFAULT ''"),
    ("renders", "paused", "INTEGER NOT NULL DEFAULT 0"),
    ("renders", "pool", "TEXT NOT NULL DEFAULT ''"),
    ("renders", "requires", "TEXT NOT NULL DEFAULT ''"),
    ("renders", "notify", "TEXT NOT NULL DEFAULT ''"),
    ("renders", "preview_every", "INTEGER NOT NULL DEFAULT 0"),
    ("renders", "preview_spp", "INTEGER NOT NULL DEFAULT 0"),
    ("renders", "preview_target", "REAL NOT NULL DEFAULT 0"),
    ("renders", "final_error", "REAL NOT NULL DEFAULT 0"),
    ("renders", "final_error_bound", "REAL NOT NULL DEFAULT 0"),
];

/// A finished or cancelled render no longer needs its scene, which `Write::CollectScenes`
/// deletes: the schema's `REFERENCES scenes(hash)` is not enforced (submit checks the scene is
/// there itself). Every connection that writes says so: the bundled SQLite enforces them by
/// default, and the writer's collections failed while only the store's connection said it.
fn unenforced_references(db: &Connection) -> rusqlite::Result<()> {
    db.execute_batch("PRAGMA foreign_keys = OFF;")
}

/// How a connection to `tessera.db` commits: WAL, every commit synced with `fsync`, and waiting
/// up to 30 s for the other connection's locks (the store and the result writer both write).
fn set_durability(db: &Connection, fsync: bool) -> rusqlite::Result<()> {
    db.busy_timeout(std::time::Duration::from_secs(30))?;
    unenforced_references(db)?;
    let mode = if fsync { "FULL" } else { "NORMAL" };
    db.execute_batch(&format!("PRAGMA journal_mode = WAL; PRAGMA synchronous = {mode};"))
}

/// Inserts one result with its checksum (the store's and the result writer's one way to),
/// unless `worker` is blocked.
fn insert_result(
    db: &Connection,
    render: i64,
    result: &StoredResult,
    sums: &[u8],
    worker: &str,
    unchecked: bool,
) -> rusqlite::Result<()> {
    let checksum = result_checksum(render, result, sums);
    db.execute(
        "INSERT INTO results (render, tile, first_pass, pass_count, sums, checksum, worker, unchecked)
         SELECT ?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8 WHERE NOT EXISTS (SELECT 1 FROM blocked_workers WHERE worker = ?7)",
        params![render, result.tile, result.first, result.count, sums, checksum, worker, unchecked],
    )?;
    Ok(())
}

fn unix_now() -> i64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs() as i64)
}

/// The checksum stored with a result: its key and its bytes, so that a flipped bit in either is
/// caught when the result is read back.
fn result_checksum(render: i64, r: &StoredResult, sums: &[u8]) -> Vec<u8> {
    let mut h = blake3::Hasher::new();
    h.update(b"tessera result v1");
    for v in [render as u64, r.tile as u64, r.first as u64, r.count as u64] {
        h.update(&v.to_le_bytes());
    }
    h.update(sums);
    h.finalize().as_bytes().to_vec()
}

impl Store {
    /// Opens (or creates) `tessera.db` in `dir`. In WAL mode a commit survives the coordinator
    /// being killed; `fsync_every_commit` also makes it survive a power cut, at about 60% of the
    /// throughput (`tessera bench coordinator`).
    ///
    /// A database that is missing or empty where anything says it held something is refused: it
    /// was lost or truncated, and starting afresh would silently forget every render. The
    /// evidence: the marker written beside it when its schema was made ([`CREATED`]), render
    /// images, and a write-ahead log it left.
    pub fn open(dir: &Path, fsync_every_commit: bool) -> Result<Self, StoreError> {
        let path = dir.join("tessera.db");
        let size = std::fs::metadata(&path).map_or(0, |m| m.len());
        if size == 0
            && let Some(evidence) = held_something(dir)
        {
            let state = if path.exists() { "is empty (0 bytes)" } else { "is missing" };
            return Err(StoreError::Unusable(format!(
                "{} {state}, but {evidence}: the database was lost or truncated. Restore it from a backup; or, to start \
                 afresh and forget its renders, move {} aside",
                path.display(),
                dir.display()
            )));
        }
        let opened = Self::with_connection(Connection::open(&path)?).and_then(|store| {
            set_durability(&store.db, fsync_every_commit)?;
            Ok(store)
        });
        let opened = opened.and_then(|store| {
            // Made now, or (a database from before the marker) found whole: say so beside it.
            let marker = dir.join(CREATED);
            if !marker.exists() {
                std::fs::write(&marker, b"tessera.db was created in this directory\n")
                    .map_err(|e| StoreError::Unusable(format!("cannot write {}: {e}", marker.display())))?;
            }
            Ok(store)
        });
        opened.map_err(|e| match e {
            StoreError::Sql(rusqlite::Error::SqliteFailure(f, _))
                if matches!(f.code, rusqlite::ErrorCode::NotADatabase | rusqlite::ErrorCode::DatabaseCorrupt) =>
            {
                StoreError::Unusable(format!(
                    "{} is not a readable SQLite database ({f}): restore it from a backup; or, to start afresh, \
                     move it and {} aside",
                    path.display(),
                    dir.join("renders").display()
                ))
            }
            e => e,
        })
    }

    pub fn in_memory() -> Result<Self, StoreError> {
        Self::with_connection(Connection::open_in_memory()?)
    }

    fn with_connection(db: Connection) -> Result<Self, StoreError> {
        let uploads_known: bool =
            db.query_row("SELECT COUNT(*) FROM sqlite_master WHERE name = 'scene_uploads'", [], |r| {
                r.get::<_, i64>(0)
            })? > 0;
        db.execute_batch(SCHEMA)?;
        db.execute_batch(log::SCHEMA)?;
        unenforced_references(&db)?;
        for (table, column, kind) in ADDED_COLUMNS {
            let present: bool = db.query_row(
                &format!("SELECT COUNT(*) FROM pragma_table_info('{table}') WHERE name = ?1"),
                [column],
                |r| r.get::<_, i64>(0),
            )? > 0;
            if !present {
                db.execute_batch(&format!("ALTER TABLE {table} ADD COLUMN {column} {kind};"))?;
            }
        }
        if !uploads_known {
            // A database from before uploads were recorded: a scene counts as uploaded by the
            // owners of the renders that use it.
            db.execute(
                "INSERT OR IGNORE INTO scene_uploads (hash, owner)
                 SELECT DISTINCT scene_hash, owner FROM renders WHERE scene_hash IN (SELECT hash FROM scenes)",
                [],
            )?;
        }
        Ok(Self { db })
    }

    /// Makes one change at once, in a transaction of its own (a sequence's renders go in
    /// together, as the writer's group commit puts them).
    pub fn apply(&self, w: &Write) -> Result<(), StoreError> {
        let tx = self.db.unchecked_transaction()?;
        match apply(&tx, w).and_then(|()| tx.commit()) {
            Err(rusqlite::Error::QueryReturnedNoRows) => match w {
                Write::State { render, .. } => Err(StoreError::NoSuchRender(*render)),
                _ => Err(StoreError::Sql(rusqlite::Error::QueryReturnedNoRows)),
            },
            done => Ok(done?),
        }
    }

    /// A second connection to the store in `dir` for reading (scenes, and the results a film is
    /// rebuilt from) outside the coordinator's state lock. The store must have created it.
    pub fn reader(dir: &Path) -> Result<Self, StoreError> {
        let db = Connection::open(dir.join("tessera.db"))?;
        db.busy_timeout(std::time::Duration::from_secs(30))?;
        unenforced_references(&db)?;
        Ok(Self { db })
    }

    /// The largest render id stored (0 when none is).
    pub fn max_render_id(&self) -> Result<i64, StoreError> {
        Ok(self.db.query_row("SELECT COALESCE(MAX(id), 0) FROM renders", [], |r| r.get(0))?)
    }

    pub fn has_scene(&self, hash: &str) -> Result<bool, StoreError> {
        Ok(self.db.query_row("SELECT 1 FROM scenes WHERE hash = ?1", [hash], |_| Ok(())).optional()?.is_some())
    }

    /// Whether `owner` uploaded the scene `hash` (and it is still stored).
    pub fn uploaded(&self, hash: &str, owner: &str) -> Result<bool, StoreError> {
        Ok(self
            .db
            .query_row("SELECT 1 FROM scene_uploads WHERE hash = ?1 AND owner = ?2", [hash, owner], |_| Ok(()))
            .optional()?
            .is_some())
    }

    pub fn scene(&self, hash: &str) -> Result<Option<Vec<u8>>, StoreError> {
        Ok(self.db.query_row("SELECT bytes FROM scenes WHERE hash = ?1", [hash], |r| r.get(0)).optional()?)
    }

    pub fn renders(&self) -> Result<Vec<StoredRender>, StoreError> {
        let mut stmt = self.db.prepare(
            "SELECT id, scene_hash, scene_name, settings, spp, tile_size, pass_spp, priority, state, target_error, min_spp, message, owner, sequence,
                    submitted_at, started_at, ended_at, name, paused, pool, requires, notify, preview_every, preview_spp, preview_target,
                    final_error, final_error_bound
             FROM renders ORDER BY id",
        )?;
        let rows = stmt.query_map([], |r| {
            Ok(StoredRender {
                id: r.get(0)?,
                scene_hash: r.get(1)?,
                scene_name: r.get(2)?,
                settings: r.get(3)?,
                spp: r.get(4)?,
                tile_size: r.get(5)?,
                pass_spp: r.get(6)?,
                priority: r.get(7)?,
                state: r.get(8)?,
                target_error: r.get(9)?,
                min_spp: r.get(10)?,
                message: r.get(11)?,
                owner: r.get(12)?,
                sequence: r.get(13)?,
                submitted_at: r.get(14)?,
                started_at: r.get(15)?,
                ended_at: r.get(16)?,
                name: r.get(17)?,
                paused: r.get(18)?,
                pool: r.get(19)?,
                requires: r.get(20)?,
                notify: r.get(21)?,
                preview_every: r.get(22)?,
                preview_spp: r.get(23)?,
                preview_target: r.get(24)?,
                // As `Write::FinalError` keeps them: infinities as the largest finite values.
                final_error: [r.get::<_, f64>(25)?, r.get(26)?]
                    .map(|v| if v.abs() == f64::MAX { f64::INFINITY.copysign(v) } else { v }),
            })
        })?;
        Ok(rows.collect::<Result<_, _>>()?)
    }

    /// Commits one accepted job result, its sums as `encode_tile_sums` wrote them. Returns once
    /// it is committed; only then may the worker be told it was merged.
    pub fn put_result(&self, render: i64, result: &StoredResult, encoded_sums: &[u8]) -> Result<(), StoreError> {
        Ok(insert_result(&self.db, render, result, encoded_sums, "", false)?)
    }

    /// The workers blocked for the farm, and why.
    pub fn blocked_workers(&self) -> Result<Vec<(String, String)>, StoreError> {
        let mut stmt = self.db.prepare("SELECT worker, why FROM blocked_workers ORDER BY blocked_at")?;
        let rows = stmt.query_map([], |r| Ok((r.get(0)?, r.get(1)?)))?;
        Ok(rows.collect::<Result<_, _>>()?)
    }

    /// The lines of a log after line `after`, at most `limit`.
    pub fn log(&self, of: LogOf, after: i64, limit: i64) -> Result<LogPage, StoreError> {
        log::read(&self.db, of, after, limit)
    }

    /// The renders holding results of `worker`.
    pub fn renders_of_worker(&self, worker: &str) -> Result<Vec<i64>, StoreError> {
        let mut stmt = self.db.prepare("SELECT DISTINCT render FROM results WHERE worker = ?1")?;
        let rows = stmt.query_map([worker], |r| r.get(0))?;
        Ok(rows.collect::<Result<_, _>>()?)
    }

    /// For each of `renders`, the workers (their ids) whose results it holds: who rendered a
    /// frame. One statement for them all.
    pub fn workers_of(&self, renders: &[i64]) -> Result<Vec<Vec<String>>, StoreError> {
        let mut stmt = self.db.prepare("SELECT DISTINCT worker FROM results WHERE render = ?1 AND worker != ''")?;
        renders.iter().map(|&render| Ok(stmt.query_map([render], |r| r.get(0))?.collect::<Result<_, _>>()?)).collect()
    }

    /// A render's results still to be checked by a second worker, with the digests of their
    /// sums. One that does not decode is left to [`Store::rebuild`], which drops it.
    pub fn unchecked(&self, render: i64) -> Result<Vec<Unchecked>, StoreError> {
        let mut stmt = self.db.prepare(
            "SELECT tile, first_pass, pass_count, worker, sums FROM results WHERE render = ?1 AND unchecked = 1",
        )?;
        let mut rows = stmt.query([render])?;
        let mut out = Vec::new();
        while let Some(row) = rows.next()? {
            let result = StoredResult { tile: row.get(0)?, first: row.get(1)?, count: row.get(2)? };
            let bytes: Vec<u8> = row.get(4)?;
            if let Ok(sums) = decode_tile_sums(&bytes) {
                out.push(Unchecked { result, worker: row.get(3)?, digest: tessera_proto::sums::digest(&sums) });
            }
        }
        Ok(out)
    }

    /// The sums of one tile over the stored results whose first pass lies below `below_pass`.
    pub fn tile_sums(
        &self,
        render: i64,
        tile: tessera_render::Tile,
        index: u32,
        below_pass: u32,
    ) -> Result<tessera_render::TileSums, StoreError> {
        let mut stmt =
            self.db.prepare("SELECT sums FROM results WHERE render = ?1 AND tile = ?2 AND first_pass < ?3")?;
        let mut rows = stmt.query(params![render, index, below_pass])?;
        let mut total = tessera_render::TileSums::new(tile);
        while let Some(row) = rows.next()? {
            let bytes: Vec<u8> = row.get(0)?;
            let sums = decode_tile_sums(&bytes).map_err(|e| StoreError::Corrupt { render, message: e.to_string() })?;
            if sums.tile != tile {
                return Err(StoreError::Corrupt {
                    render,
                    message: format!("a result of tile {index} covers {:?}", sums.tile),
                });
            }
            total.merge(&sums);
        }
        Ok(total)
    }

    /// The job ranges of a render's stored results, without their sums.
    pub fn ranges(&self, render: i64) -> Result<Vec<StoredResult>, StoreError> {
        let mut stmt =
            self.db.prepare("SELECT tile, first_pass, pass_count FROM results WHERE render = ?1 ORDER BY rowid")?;
        let rows =
            stmt.query_map([render], |r| Ok(StoredResult { tile: r.get(0)?, first: r.get(1)?, count: r.get(2)? }))?;
        Ok(rows.collect::<Result<_, _>>()?)
    }

    /// Every stored result of a render, merged into `empty` (its film, of its size and layers),
    /// with the job ranges it covered.
    ///
    /// A result whose checksum does not match, or whose sums do not decode, is deleted and left
    /// out (its passes are then pending again), and the log says so; results stored before
    /// checksums existed are checked by decoding alone. Each row is read once for both.
    pub fn rebuild(&self, render: i64, empty: Film) -> Result<(Film, Vec<StoredResult>), StoreError> {
        let mut film = empty;
        let mut ranges = Vec::new();
        let mut bad = Vec::new();
        {
            let mut stmt = self.db.prepare(
                "SELECT rowid, tile, first_pass, pass_count, sums, checksum FROM results WHERE render = ?1 ORDER BY rowid",
            )?;
            let mut rows = stmt.query([render])?;
            while let Some(row) = rows.next()? {
                let range = StoredResult { tile: row.get(1)?, first: row.get(2)?, count: row.get(3)? };
                let bytes: Vec<u8> = row.get(4)?;
                let checksum: Option<Vec<u8>> = row.get(5)?;
                let sums = match checksum {
                    Some(c) if c != result_checksum(render, &range, &bytes) => {
                        Err("its checksum does not match".into())
                    }
                    _ => decode_tile_sums(&bytes).map_err(|e| e.to_string()),
                };
                match sums {
                    Ok(sums) => {
                        film.merge_tile(&sums).map_err(|e| StoreError::Corrupt { render, message: e.to_string() })?;
                        ranges.push(range);
                    }
                    Err(why) => bad.push((row.get::<_, i64>(0)?, range, why)),
                }
            }
        }
        for (rowid, range, why) in bad {
            self.db.execute("DELETE FROM results WHERE rowid = ?1", [rowid])?;
            tracing::warn!(
                render,
                "dropped a corrupt stored result (tile {}, passes {}..{}): {why}; its passes will be rendered again",
                range.tile,
                range.first,
                range.first + range.count
            );
        }
        Ok((film, ranges))
    }
}

/// What [`backup`] copied.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Backup {
    pub renders: u64,
    pub results: u64,
    pub scenes: u64,
    pub bytes: u64,
}

/// Writes a consistent copy of the store in `dir` to `dest` (made if need be; it must not hold a
/// database yet): `tessera.db` as one snapshot taken in a single read transaction (SQLite's
/// `VACUUM INTO`, so it may run while the coordinator serves and writes), and the marker that
/// says a database was made there. A coordinator started on `dest` resumes every render as the
/// snapshot had it; finished images are rebuilt from the stored results when fetched.
pub fn backup(dir: &Path, dest: &Path) -> Result<Backup, StoreError> {
    let source = dir.join("tessera.db");
    if !source.is_file() {
        return Err(StoreError::Unusable(format!(
            "{} does not exist: give the coordinator's --data-dir",
            source.display()
        )));
    }
    let target = dest.join("tessera.db");
    if target.exists() {
        return Err(StoreError::Unusable(format!(
            "{} already exists: back up into a new or empty directory",
            target.display()
        )));
    }
    std::fs::create_dir_all(dest)
        .map_err(|e| StoreError::Unusable(format!("cannot create {}: {e}", dest.display())))?;
    let db = Connection::open_with_flags(&source, rusqlite::OpenFlags::SQLITE_OPEN_READ_WRITE)?;
    db.busy_timeout(std::time::Duration::from_secs(30))?;
    let target_text =
        target.to_str().ok_or_else(|| StoreError::Unusable(format!("{} is not a UTF-8 path", target.display())))?;
    db.execute("VACUUM INTO ?1", [target_text])?;
    drop(db);
    let copy = Connection::open_with_flags(&target, rusqlite::OpenFlags::SQLITE_OPEN_READ_ONLY)?;
    let count = |table: &str| -> Result<u64, StoreError> {
        Ok(copy.query_row(&format!("SELECT COUNT(*) FROM {table}"), [], |r| r.get::<_, i64>(0))? as u64)
    };
    let (renders, results, scenes) = (count("renders")?, count("results")?, count("scenes")?);
    let integrity: String = copy.query_row("PRAGMA integrity_check", [], |r| r.get(0))?;
    if integrity != "ok" {
        return Err(StoreError::Unusable(format!(
            "the copy {} failed its integrity check: {integrity}",
            target.display()
        )));
    }
    std::fs::write(dest.join(CREATED), b"tessera.db was created in this directory (a backup)\n")
        .map_err(|e| StoreError::Unusable(format!("cannot write {}: {e}", dest.join(CREATED).display())))?;
    let bytes = std::fs::metadata(&target).map_or(0, |m| m.len());
    Ok(Backup { renders, results, scenes, bytes })
}

/// The file a coordinator holds locked while it uses a data directory, with its pid in it.
pub const LOCK: &str = "tessera.lock";

/// Takes the data directory `dir` for this process: a second coordinator on the same directory
/// would interleave its writes with the first's (two processes giving out the same render ids),
/// so it is refused, naming the holder's pid. The lock is the operating system's (`flock`): it
/// goes with the returned file, or with the process however it ends.
pub fn lock_data_dir(dir: &Path) -> Result<std::fs::File, StoreError> {
    use std::io::{Read, Seek, Write as _};
    let path = dir.join(LOCK);
    let unusable = |e: std::io::Error| StoreError::Unusable(format!("cannot lock {}: {e}", path.display()));
    let mut file = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(&path)
        .map_err(unusable)?;
    match file.try_lock() {
        Ok(()) => {
            file.set_len(0).map_err(unusable)?;
            file.rewind().map_err(unusable)?;
            writeln!(file, "{}", std::process::id()).map_err(unusable)?;
            Ok(file)
        }
        Err(std::fs::TryLockError::WouldBlock) => {
            let mut holder = String::new();
            let _ = file.read_to_string(&mut holder);
            let holder = holder.trim();
            let who = if holder.is_empty() { "another process".to_string() } else { format!("process {holder}") };
            Err(StoreError::Unusable(format!(
                "{} is in use by another coordinator ({who} holds {}): stop it first, or give this one another \
                 --data-dir",
                dir.display(),
                path.display()
            )))
        }
        Err(std::fs::TryLockError::Error(e)) => Err(unusable(e)),
    }
}

/// The marker a store leaves beside `tessera.db` once its schema exists: a database missing or
/// empty beside it was lost.
pub const CREATED: &str = "tessera.db.created";

/// What in `dir` says its database held something, if anything does.
fn held_something(dir: &Path) -> Option<String> {
    let images = std::fs::read_dir(dir.join("renders")).map_or(0, |d| d.flatten().count());
    let wal = std::fs::metadata(dir.join("tessera.db-wal")).map_or(0, |m| m.len());
    if dir.join(CREATED).exists() {
        Some(format!("{} says a database was made here", dir.join(CREATED).display()))
    } else if images > 0 {
        Some(format!("{} holds {images} render file(s)", dir.join("renders").display()))
    } else if wal > 0 {
        Some(format!("its write-ahead log {} holds {wal} bytes", dir.join("tessera.db-wal").display()))
    } else {
        None
    }
}

#[cfg(test)]
mod tests;
