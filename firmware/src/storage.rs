//! Power-cut-safe storage of the parameter blob in the state directory.
//!
//! Files: `params.irp` (active set) and `params.prev.irp` (the set before it, for rollback).
//! Every file is replaced by writing `*.tmp`, fsync, rename, fsync of the directory, so a power
//! cut leaves either the old or the new complete file. The previous set is saved before the
//! active one is replaced, so at every instant at least one complete set is on disk.

use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::error::{FirmwareError, Result};

/// The active parameter set's file in the state directory.
pub const ACTIVE_FILE: &str = "params.irp";
/// The set before it, kept for rollback.
pub const PREVIOUS_FILE: &str = "params.prev.irp";

/// Which stored file a blob came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StoredSlot {
    /// [`ACTIVE_FILE`]: the set in use.
    Active,
    /// [`PREVIOUS_FILE`]: the set before it, for rollback.
    Previous,
}

/// The parameter files in the state directory, replaced atomically (see the module docs).
#[derive(Debug, Clone)]
pub struct ParamStore {
    dir: PathBuf,
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> FirmwareError + '_ {
    move |source| FirmwareError::Storage {
        path: path.display().to_string(),
        source,
    }
}

impl ParamStore {
    /// Creates the directory if needed.
    pub fn open(dir: impl Into<PathBuf>) -> Result<Self> {
        let dir = dir.into();
        fs::create_dir_all(&dir).map_err(io_err(&dir))?;
        Ok(Self { dir })
    }

    /// The state directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The file that holds `slot`'s blob.
    pub fn path(&self, slot: StoredSlot) -> PathBuf {
        self.dir.join(match slot {
            StoredSlot::Active => ACTIVE_FILE,
            StoredSlot::Previous => PREVIOUS_FILE,
        })
    }

    /// Reads a stored blob; `Ok(None)` when the file does not exist.
    pub fn read(&self, slot: StoredSlot) -> Result<Option<Vec<u8>>> {
        let p = self.path(slot);
        match fs::read(&p) {
            Ok(b) => Ok(Some(b)),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(io_err(&p)(e)),
        }
    }

    /// Stores `blob` as the active set, keeping the current active set as the previous one.
    pub fn store(&self, blob: &[u8]) -> Result<()> {
        if let Some(current) = self.read(StoredSlot::Active)? {
            self.replace_file(&self.path(StoredSlot::Previous), &current)?;
        }
        self.replace_file(&self.path(StoredSlot::Active), blob)
    }

    fn replace_file(&self, target: &Path, data: &[u8]) -> Result<()> {
        let mut tmp_name = target.as_os_str().to_owned();
        tmp_name.push(".tmp");
        let tmp = PathBuf::from(tmp_name);
        {
            let mut f = File::create(&tmp).map_err(io_err(&tmp))?;
            f.write_all(data).map_err(io_err(&tmp))?;
            f.sync_all().map_err(io_err(&tmp))?;
        }
        fs::rename(&tmp, target).map_err(io_err(target))?;
        // The rename is durable only once the directory entry is on disk.
        File::open(&self.dir)
            .and_then(|d| d.sync_all())
            .map_err(io_err(&self.dir))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn store_keeps_previous_and_leaves_no_temp_files() {
        let dir = std::env::temp_dir().join(format!("irtrackd-store-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        let store = ParamStore::open(&dir).unwrap();
        assert_eq!(store.read(StoredSlot::Active).unwrap(), None);
        store.store(b"one").unwrap();
        assert_eq!(
            store.read(StoredSlot::Active).unwrap().as_deref(),
            Some(&b"one"[..])
        );
        assert_eq!(store.read(StoredSlot::Previous).unwrap(), None);
        store.store(b"two").unwrap();
        assert_eq!(
            store.read(StoredSlot::Active).unwrap().as_deref(),
            Some(&b"two"[..])
        );
        assert_eq!(
            store.read(StoredSlot::Previous).unwrap().as_deref(),
            Some(&b"one"[..])
        );
        let names: Vec<_> = fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names.len(), 2, "{names:?}");
        fs::remove_dir_all(&dir).unwrap();
    }
}
