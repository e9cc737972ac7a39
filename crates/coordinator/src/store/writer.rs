//! The store's writer: the coordinator's changes made on a thread of their own, in order, many
//! to a transaction.

use super::{StoreError, Write, apply, set_durability};
use rusqlite::Connection;
use std::path::Path;

/// Who waits for a commit (or a checkpoint), if anyone does.
type Done = Option<tokio::sync::oneshot::Sender<Result<(), String>>>;

/// One change on its way to the database, and who waits for its commit.
struct Pending {
    write: Write,
    done: Done,
}

/// What the writer's thread is asked to do: a change, or a checkpoint once every change queued
/// before it is committed.
enum Job {
    Write(Pending),
    Checkpoint(Done),
}

/// Makes the store's changes on a thread of its own, outside the coordinator's state lock, in
/// the order they were queued and many to a transaction (group commit): changes that arrive while
/// one transaction commits go into the next, so a busy coordinator pays one commit (and, with
/// fsync, one sync) for many results.
pub struct Writer {
    queue: std::sync::mpsc::Sender<Job>,
    thread: Option<std::thread::JoinHandle<()>>,
}

/// Most changes in one transaction.
const GROUP: usize = 256;
/// The name of the writer's thread.
pub const WRITER_THREAD: &str = "tessera-results";

impl Writer {
    /// Opens a second connection to `dir/tessera.db` (the store must have created it) and
    /// starts the writing thread. When the writer is dropped, it commits what is queued and
    /// checkpoints the database.
    pub fn start(dir: &Path, fsync_every_commit: bool) -> Result<Self, StoreError> {
        let mut db = Connection::open(dir.join("tessera.db"))?;
        set_durability(&db, fsync_every_commit)?;
        let (queue, jobs) = std::sync::mpsc::channel::<Job>();
        let thread = std::thread::Builder::new()
            .name(WRITER_THREAD.into())
            .spawn(move || {
                // A checkpoint met while a group is gathered waits for that group's commit.
                let mut after_group = None;
                while let Some(job) = after_group.take().or_else(|| jobs.recv().ok()) {
                    match job {
                        Job::Checkpoint(done) => answer(done, checkpoint(&db)),
                        Job::Write(first) => {
                            let mut group = vec![first];
                            while group.len() < GROUP {
                                match jobs.try_recv() {
                                    Ok(Job::Write(p)) => group.push(p),
                                    Ok(checkpoint) => {
                                        after_group = Some(checkpoint);
                                        break;
                                    }
                                    Err(_) => break,
                                }
                            }
                            commit_group(&mut db, group);
                        }
                    }
                }
                if let Err(e) = checkpoint(&db) {
                    tracing::warn!("the database was not checkpointed at the end: {e}");
                }
            })
            .map_err(|e| StoreError::Unusable(format!("cannot start the store's writer: {e}")))?;
        Ok(Self { queue, thread: Some(thread) })
    }

    /// Queues a change; the receiver says when it is committed (or why it is not).
    pub fn commit(&self, write: Write) -> tokio::sync::oneshot::Receiver<Result<(), String>> {
        let (done, receiver) = tokio::sync::oneshot::channel();
        self.queue_write(write, Some(done));
        receiver
    }

    /// Queues a change no one waits for: a failure is logged.
    pub fn queue(&self, write: Write) {
        self.queue_write(write, None);
    }

    fn queue_write(&self, write: Write, done: Done) {
        if let Err(std::sync::mpsc::SendError(Job::Write(p))) = self.queue.send(Job::Write(Pending { write, done })) {
            tell(p, Err("the store's writer has stopped".into()));
        }
    }

    /// Once every change queued before is committed, moves the write-ahead log into
    /// `tessera.db` and empties it: the file alone then holds everything (what a graceful stop
    /// does, so that a copy of `tessera.db` alone loses nothing).
    pub fn checkpoint(&self) -> tokio::sync::oneshot::Receiver<Result<(), String>> {
        let (done, receiver) = tokio::sync::oneshot::channel();
        if let Err(std::sync::mpsc::SendError(Job::Checkpoint(done))) = self.queue.send(Job::Checkpoint(Some(done))) {
            answer(done, Err("the store's writer has stopped".into()));
        }
        receiver
    }
}

/// A writer dropped first commits every change queued, then checkpoints: the store then holds
/// all it was told, in `tessera.db` itself.
impl Drop for Writer {
    fn drop(&mut self) {
        let (closed, _) = std::sync::mpsc::channel();
        drop(std::mem::replace(&mut self.queue, closed));
        if let Some(thread) = self.thread.take()
            && thread.join().is_err()
        {
            tracing::error!("the store's writer panicked");
        }
    }
}

/// Copies the whole write-ahead log into the database file and truncates the log; fails if a
/// reader kept part of it in use past the busy timeout.
fn checkpoint(db: &Connection) -> Result<(), String> {
    let (busy, log, moved): (i64, i64, i64) = db
        .query_row("PRAGMA wal_checkpoint(TRUNCATE)", [], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)))
        .map_err(|e| format!("database: {e}"))?;
    if busy != 0 {
        return Err(format!("readers kept the write-ahead log in use ({moved} of {log} pages moved)"));
    }
    Ok(())
}

fn answer(done: Done, result: Result<(), String>) {
    if let Some(done) = done {
        let _ = done.send(result);
    } else if let Err(e) = result {
        tracing::warn!("{e}");
    }
}

/// Tells whoever waits for `p` how its commit went, or logs a failure no one waits for.
fn tell(p: Pending, result: Result<(), String>) {
    match (p.done, result) {
        (Some(done), result) => {
            let _ = done.send(result);
        }
        (None, Err(e)) => tracing::error!("could not store {}: {e}", describe(&p.write)),
        (None, Ok(())) => {}
    }
}

/// What a change is, for the log.
fn describe(w: &Write) -> String {
    match w {
        Write::Result { render, result, .. } => format!("a result of render {render} (tile {})", result.tile),
        Write::Renders(r) => format!("{} new render(s)", r.len()),
        Write::State { render, state, .. } => format!("render {render} as {state}"),
        Write::Quality { render, spp, .. } => format!("render {render} refined to {spp} spp"),
        Write::Scene { hash, .. } => format!("scene {hash}"),
        Write::TouchScene(hash) => format!("the time of scene {hash}"),
        Write::DeleteScene(hash) => format!("the deletion of scene {hash}"),
        Write::CollectScenes { .. } => "the collection of unused scenes".into(),
        Write::Checked { render, tile, first } => format!("the check of render {render} tile {tile} pass {first}"),
        Write::Started { render, .. } => format!("the start of render {render}"),
        Write::Ended { render, .. } => format!("the end of render {render}"),
        Write::FinalError { render, .. } => format!("the error of render {render}"),
        Write::Log { of, .. } => format!("a line of render {}'s log", of.id),
        Write::Steer { target, paused, priority } => {
            format!("render {target}'s steering (priority {priority}, paused {paused})")
        }
        Write::Block { worker, .. } => format!("the block of worker {}", worker.escape_debug()),
    }
}

/// Commits `group` in one transaction; if that fails, each change alone, so that one bad row
/// fails only its own commit.
fn commit_group(db: &mut Connection, group: Vec<Pending>) {
    let together = db.transaction().and_then(|tx| {
        for p in &group {
            apply(&tx, &p.write)?;
        }
        tx.commit()
    });
    if together.is_ok() {
        for p in group {
            tell(p, Ok(()));
        }
        return;
    }
    for p in group {
        let alone = db.transaction().and_then(|tx| {
            apply(&tx, &p.write)?;
            tx.commit()
        });
        tell(p, alone.map_err(|e| format!("database: {e}")));
    }
}
