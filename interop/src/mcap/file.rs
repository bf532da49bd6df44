//! How a recording reaches its file so that a failed write (a full disk) never costs what was
//! written before: the MCAP writer's bytes are held in memory and written to the file one
//! closed chunk at a time, each followed by an end — Data End, a Footer without summary and
//! the closing magic — that the next chunk overwrites. After every chunk the file is a
//! complete MCAP that PyPI's `mcap`, Foxglove and the `mcap` CLI read linearly; the summary
//! (statistics, indexes) is added when the recording is finished.
//!
//! A write that fails part-way (no space left) is undone: the file is cut back to the last
//! whole chunk and the end written again, into space the file held already.

use std::io::{Seek, SeekFrom, Write};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

/// Length of [`END`].
pub const END_LEN: usize = 50;

/// What follows every committed chunk (MCAP spec, little-endian): a Data End record (opcode
/// 0x0F, length 4, data section CRC 0 = not computed), a Footer (opcode 0x02, length 20,
/// summary start 0 = no summary, summary offset start 0, summary CRC 0) and the magic.
pub const END: [u8; END_LEN] = [
    0x0F, 4, 0, 0, 0, 0, 0, 0, 0, // Data End, length 4
    0, 0, 0, 0, // data_section_crc
    0x02, 20, 0, 0, 0, 0, 0, 0, 0, // Footer, length 20
    0, 0, 0, 0, 0, 0, 0, 0, // summary_start
    0, 0, 0, 0, 0, 0, 0, 0, // summary_offset_start
    0, 0, 0, 0, // summary_crc
    0x89, b'M', b'C', b'A', b'P', b'0', b'\r', b'\n',
];

/// A file a recording is written into: positioned writes and cutting back. Implemented for
/// [`std::fs::File`]; tests use size-limited or blocking stand-ins.
pub trait RecordingFile: Send {
    /// Writes all of `data` at `offset_bytes` (a short write is an error).
    fn write_all_at_offset(&mut self, offset_bytes: u64, data: &[u8]) -> std::io::Result<()>;
    /// Cuts the file to `len_bytes` (frees what lay beyond).
    fn truncate_to(&mut self, len_bytes: u64) -> std::io::Result<()>;
}

impl RecordingFile for std::fs::File {
    fn write_all_at_offset(&mut self, offset_bytes: u64, data: &[u8]) -> std::io::Result<()> {
        self.seek(SeekFrom::Start(offset_bytes))?;
        self.write_all(data)
    }
    fn truncate_to(&mut self, len_bytes: u64) -> std::io::Result<()> {
        std::fs::File::set_len(self, len_bytes)
    }
}

impl<T: RecordingFile + ?Sized> RecordingFile for Box<T> {
    fn write_all_at_offset(&mut self, offset_bytes: u64, data: &[u8]) -> std::io::Result<()> {
        (**self).write_all_at_offset(offset_bytes, data)
    }
    fn truncate_to(&mut self, len_bytes: u64) -> std::io::Result<()> {
        (**self).truncate_to(len_bytes)
    }
}

/// What a failed write left on file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Kept {
    /// The I/O error, as the OS words it.
    pub reason: String,
    /// Bytes of whole chunks (and the header) that stay readable.
    pub bytes: u64,
    /// Chunks (commits) that stay readable; 0: the file holds nothing readable (it was cut to
    /// zero length and can be removed).
    pub commits: u64,
    /// The end (Data End, Footer, magic) was written again after them: readers open the file
    /// as it is. `false`: even that failed; `mcap recover` still reads the chunks.
    pub end_written: bool,
}

/// The MCAP writer's output stream: appends into memory; `flush` (the writer's after closing
/// a chunk) commits to the file.
pub(crate) struct CommitSink<F: RecordingFile> {
    file: F,
    /// Bytes the writer produced since the last commit.
    pending: Vec<u8>,
    /// Bytes the writer produced in all (its stream position).
    position: u64,
    /// Bytes of whole records on file; [`END`] follows them.
    committed: u64,
    commits: u64,
    /// Set by a failed commit; every later write fails.
    stopped: Option<Kept>,
    /// Set while the writer writes its summary: its own footer and magic end the file, so
    /// its closing flush adds no [`END`].
    finishing: Arc<AtomicBool>,
}

impl<F: RecordingFile> CommitSink<F> {
    pub(crate) fn new(file: F) -> Self {
        Self {
            file,
            pending: Vec::with_capacity(64 * 1024),
            position: 0,
            committed: 0,
            commits: 0,
            stopped: None,
            finishing: Arc::new(AtomicBool::new(false)),
        }
    }

    /// The flag that makes the next flush the file's last commit (see `finishing`).
    pub(crate) fn finishing_flag(&self) -> Arc<AtomicBool> {
        self.finishing.clone()
    }

    /// Why writing stopped, if it did.
    pub(crate) fn stopped(&self) -> Option<&Kept> {
        self.stopped.as_ref()
    }

    fn refuse(&self) -> std::io::Result<()> {
        match &self.stopped {
            Some(k) => Err(std::io::Error::other(format!(
                "recording stopped after an earlier write failure: {}",
                k.reason
            ))),
            None => Ok(()),
        }
    }

    /// Writes what is pending after the last commit, followed by [`END`] unless `last`
    /// (the writer's own summary and footer end the file then).
    fn commit(&mut self, last: bool) -> std::io::Result<()> {
        self.refuse()?;
        if self.pending.is_empty() {
            return Ok(());
        }
        let n = self.pending.len();
        if !last {
            self.pending.extend_from_slice(&END);
        }
        let res = self.file.write_all_at_offset(self.committed, &self.pending);
        self.pending.truncate(n);
        match res {
            Ok(()) => {
                self.committed += n as u64;
                self.commits += 1;
                self.pending.clear();
                Ok(())
            }
            Err(e) => {
                self.undo(&e);
                Err(e)
            }
        }
    }

    /// After a failed write: cut the file back to the whole chunks and write their end again,
    /// into space the file held before this write (the previous end was there).
    fn undo(&mut self, e: &std::io::Error) {
        let end_written = if self.commits == 0 {
            // Not even the header is whole: nothing to keep.
            let _ = self.file.truncate_to(0);
            false
        } else {
            self.file
                .truncate_to(self.committed + END_LEN as u64)
                .and_then(|()| self.file.write_all_at_offset(self.committed, &END))
                .is_ok()
        };
        self.pending.clear();
        self.stopped = Some(Kept {
            reason: e.to_string(),
            bytes: if self.commits == 0 { 0 } else { self.committed },
            commits: self.commits,
            end_written,
        });
    }

    /// Writes the writer's last bytes (summary, footer) after the last commit.
    pub(crate) fn finish(&mut self) -> std::io::Result<()> {
        self.commit(true)
    }
}

impl<F: RecordingFile> Write for CommitSink<F> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.refuse()?;
        self.pending.extend_from_slice(buf);
        self.position += buf.len() as u64;
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        let last = self.finishing.load(Ordering::Relaxed);
        self.commit(last)
    }
}

/// The writer (with seeking disabled) only asks where it is.
impl<F: RecordingFile> Seek for CommitSink<F> {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        match pos {
            SeekFrom::Current(0) | SeekFrom::End(0) => Ok(self.position),
            SeekFrom::Start(p) if p == self.position => Ok(self.position),
            _ => Err(std::io::Error::new(
                std::io::ErrorKind::Unsupported,
                "MCAP recordings are written front to back",
            )),
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// An in-memory file of at most `capacity_bytes`: a write past it stores what fits and
    /// fails with "no space", as a full filesystem does.
    #[derive(Debug, Clone)]
    pub(crate) struct SmallDisk {
        pub(crate) data: Vec<u8>,
        pub(crate) capacity_bytes: usize,
    }

    impl RecordingFile for SmallDisk {
        fn write_all_at_offset(&mut self, offset_bytes: u64, data: &[u8]) -> std::io::Result<()> {
            let at = offset_bytes as usize;
            if self.data.len() < at {
                self.data.resize(at, 0);
            }
            let room = self.capacity_bytes.saturating_sub(at);
            let n = data.len().min(room);
            let end = at + n;
            if self.data.len() < end {
                self.data.resize(end, 0);
            }
            self.data[at..end].copy_from_slice(&data[..n]);
            if n < data.len() {
                return Err(std::io::Error::from(std::io::ErrorKind::StorageFull));
            }
            Ok(())
        }
        fn truncate_to(&mut self, len_bytes: u64) -> std::io::Result<()> {
            self.data.truncate(len_bytes as usize);
            Ok(())
        }
    }

    #[test]
    fn end_is_data_end_footer_without_summary_and_magic() {
        // Field by field from the MCAP spec (records: opcode u8, length u64, body).
        let mut want = vec![0x0Fu8];
        want.extend_from_slice(&4u64.to_le_bytes());
        want.extend_from_slice(&0u32.to_le_bytes());
        want.push(0x02);
        want.extend_from_slice(&20u64.to_le_bytes());
        want.extend_from_slice(&0u64.to_le_bytes());
        want.extend_from_slice(&0u64.to_le_bytes());
        want.extend_from_slice(&0u32.to_le_bytes());
        want.extend_from_slice(b"\x89MCAP0\r\n");
        assert_eq!(END.as_slice(), want.as_slice());
    }

    #[test]
    fn each_commit_ends_the_file_and_a_failed_one_is_undone() {
        let mut sink = CommitSink::new(SmallDisk {
            data: Vec::new(),
            capacity_bytes: 150,
        });
        sink.write_all(&[1; 40]).unwrap();
        sink.flush().unwrap();
        assert_eq!(sink.file.data.len(), 40 + END_LEN);
        assert_eq!(&sink.file.data[40..], END.as_slice());
        sink.write_all(&[2; 30]).unwrap();
        sink.flush().unwrap();
        assert_eq!(sink.file.data.len(), 70 + END_LEN);
        assert_eq!(&sink.file.data[..40], [1; 40].as_slice());
        assert_eq!(&sink.file.data[70..], END.as_slice());
        // 70 + 60 + 50 > 150: the write stops at the capacity and is undone.
        sink.write_all(&[3; 60]).unwrap();
        let e = sink.flush().unwrap_err();
        assert_eq!(e.kind(), std::io::ErrorKind::StorageFull);
        assert_eq!(sink.file.data.len(), 70 + END_LEN);
        assert_eq!(&sink.file.data[70..], END.as_slice());
        let kept = sink.stopped().unwrap().clone();
        assert_eq!((kept.bytes, kept.commits, kept.end_written), (70, 2, true));
        // Later writes are refused, naming the first failure.
        let later = sink.write(&[4]).unwrap_err().to_string();
        assert!(later.contains("earlier write failure"), "{later}");
    }

    #[test]
    fn a_first_commit_that_fails_leaves_an_empty_file() {
        let mut sink = CommitSink::new(SmallDisk {
            data: Vec::new(),
            capacity_bytes: 60,
        });
        sink.write_all(&[1; 40]).unwrap();
        assert!(sink.flush().is_err());
        assert!(sink.file.data.is_empty());
        assert_eq!(sink.stopped().unwrap().commits, 0);
    }

    #[test]
    fn only_the_current_position_can_be_sought() {
        let mut sink = CommitSink::new(SmallDisk {
            data: Vec::new(),
            capacity_bytes: 100,
        });
        sink.write_all(&[1; 7]).unwrap();
        assert_eq!(sink.stream_position().unwrap(), 7);
        assert_eq!(sink.seek(SeekFrom::Start(7)).unwrap(), 7);
        assert!(sink.seek(SeekFrom::Start(0)).is_err());
    }
}
