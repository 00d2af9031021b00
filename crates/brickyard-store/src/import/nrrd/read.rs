//! NRRD data readers: locating the payload in each data file (line and
//! byte skips, size and gzip checks), positioned reads of raw rows, and
//! forward-only gzip cursors with the span kept for interleaved channels.

use super::fields::Plan;
use super::{Encoding, NrrdSource};
use crate::error::{IoContext, Result, StoreError};
use crate::import::flip::Flip;
use crate::import::raw::{ends_early, read_full_at};
use crate::import::{swap_bytes_in_place, MAX_DEFLATE_RATIO};
use crate::source::{check_region, SourceMeta, VolumeSource};
use flate2::read::MultiGzDecoder;
use std::fs::File;
use std::io::{BufRead, BufReader, ErrorKind, Read, Seek, SeekFrom};
use std::ops::Range;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, PoisonError};

/// Size of the scratch buffer used to de-interleave channels.
const CHUNK_BYTES: usize = 4 << 20;
/// Most gzip decoder cursors kept (one per channel for planar channels).
const MAX_GZ_CURSORS: usize = 256;
/// Buffer between a gzip file and its decoder.
const GZ_BUF_BYTES: usize = 64 << 10;

/// One data file and where its payload starts.
#[derive(Debug)]
pub(super) struct DataFile {
    path: PathBuf,
    /// Raw: byte offset of the payload. Gzip: byte offset of the gzip stream.
    start: u64,
}

#[derive(Default)]
pub(super) struct GzState {
    pub(super) cursor: Option<GzCursor>,
    /// A decompressed span `(payload offset, bytes)` kept so that the other
    /// channels of interleaved data can be read without decompressing again.
    cache: Option<(u64, Vec<u8>)>,
}

pub(super) struct GzCursor {
    file: usize,
    /// Decompressed bytes consumed from this file's stream (byte skip included).
    pub(super) pos: u64,
    dec: MultiGzDecoder<BufReader<File>>,
}

// ---------------------------------------------------------------------------
// Locating the data

impl NrrdSource {
    pub(super) fn new(
        path: &Path,
        file: File,
        header_end: Option<u64>,
        plan: Plan,
    ) -> Result<NrrdSource> {
        let attached = plan.data_files.is_empty();
        let (paths, first_start) = if attached {
            let Some(end) = header_end else {
                return Err(StoreError::invalid(
                    path,
                    "data",
                    "the file ends inside the header: no blank line and no data follow it, \
                     and there is no data file field",
                ));
            };
            (vec![path.to_path_buf()], end)
        } else {
            (plan.data_files.clone(), 0)
        };
        let per_file = plan.total_bytes / paths.len() as u64;
        let mut files = Vec::with_capacity(paths.len());
        let mut raw_file = None;
        let single = paths.len() == 1;
        for p in paths {
            let f = if attached {
                file.try_clone().at(path)?
            } else {
                File::open(&p).map_err(|e| data_file_error(path, &p, e))?
            };
            let start = locate(path, &p, &f, first_start, &plan, per_file, attached)?;
            if single && plan.encoding == Encoding::Raw {
                raw_file = Some(f);
            }
            files.push(DataFile { path: p, start });
        }
        let gz_slots = match plan.encoding {
            Encoding::Raw => 0,
            Encoding::Gzip if !plan.layout.interleaved => plan.meta.channels.min(MAX_GZ_CURSORS),
            Encoding::Gzip => 1,
        };
        let flip = Flip::new(plan.flip, plan.meta.dims);
        Ok(NrrdSource {
            meta: plan.meta,
            layout: plan.layout,
            encoding: plan.encoding,
            big_endian: plan.big_endian,
            files,
            per_file,
            gz_skip: plan.byte_skip.max(0) as u64,
            attached,
            raw_file,
            gz: (0..gz_slots).map(|_| Mutex::default()).collect(),
            flip,
            #[cfg(test)]
            gz_opens: Default::default(),
        })
    }

    /// Name a data file in messages: nothing when attached.
    fn where_(&self, k: usize) -> String {
        if self.attached {
            String::new()
        } else {
            format!(" in data file {}", self.files[k].path.display())
        }
    }
}

/// An I/O error on a detached data file, naming the data file and the header.
fn data_file_error(header: &Path, data: &Path, e: std::io::Error) -> StoreError {
    let source = std::io::Error::new(
        e.kind(),
        format!("{e} (data file named in {})", header.display()),
    );
    StoreError::io(data, source)
}

/// Where the payload (raw) or gzip stream starts in one data file, after
/// `line skip` and (raw) `byte skip`; checks the file is large enough (raw)
/// or starts like a gzip stream.
fn locate(
    header: &Path,
    data: &Path,
    f: &File,
    base: u64,
    plan: &Plan,
    per_file: u64,
    attached: bool,
) -> Result<u64> {
    let io_err = |e| {
        if attached {
            StoreError::io(header, e)
        } else {
            data_file_error(header, data, e)
        }
    };
    let what = if attached {
        "file".to_string()
    } else {
        format!("data file {}", data.display())
    };
    let len = f.metadata().map_err(io_err)?.len();
    let mut start = base;
    if plan.line_skip > 0 && plan.byte_skip != -1 {
        // Lines are skipped as they stream by, none kept (a line may be
        // as long as the file), and no further than the file's length (a
        // device such as /dev/zero has none, and no end).
        let mut r = BufReader::new(f);
        r.seek(SeekFrom::Start(base)).map_err(io_err)?;
        let mut r = r.take(len.saturating_sub(base));
        for k in 0..plan.line_skip {
            loop {
                let buf = r.fill_buf().map_err(io_err)?;
                if buf.is_empty() {
                    return Err(StoreError::invalid(
                        header,
                        "line skip",
                        format!(
                            "{what} ends after {k} of the {} lines to skip",
                            plan.line_skip
                        ),
                    ));
                }
                match buf.iter().position(|&b| b == b'\n') {
                    Some(i) => {
                        r.consume(i + 1);
                        start += i as u64 + 1;
                        break;
                    }
                    None => {
                        let n = buf.len();
                        r.consume(n);
                        start += n as u64;
                    }
                }
            }
        }
    }
    let after = if attached { " after the header" } else { "" };
    let per = if plan.data_files.len() > 1 {
        format!(" per file ({} files)", plan.data_files.len())
    } else {
        String::new()
    };
    match plan.encoding {
        Encoding::Raw => {
            let avail = len.saturating_sub(start);
            let skip = plan.byte_skip.max(0) as u64;
            if avail < per_file.saturating_add(skip) {
                let skipped = if skip > 0 {
                    format!(" plus {skip} (byte skip)")
                } else {
                    String::new()
                };
                return Err(StoreError::invalid(
                    header,
                    "data",
                    format!(
                        "{what} holds {avail} bytes{after} but sizes × type need {per_file}{per}{skipped}"
                    ),
                ));
            }
            Ok(if plan.byte_skip == -1 {
                len - per_file
            } else {
                start + skip
            })
        }
        Encoding::Gzip => {
            let mut magic = [0u8; 2];
            let got = f.read_at(&mut magic, start).map_err(io_err)?;
            let got = if got == 1 {
                got + f.read_at(&mut magic[1..], start + 1).map_err(io_err)?
            } else {
                got
            };
            let at = if attached || start > 0 {
                format!(" at byte {start}")
            } else {
                String::new()
            };
            if got < 2 {
                return Err(StoreError::invalid(
                    header,
                    "data",
                    format!("{what} holds no gzip stream{at}{after}: it is empty or truncated"),
                ));
            }
            if magic != [0x1f, 0x8b] {
                let in_ = if attached {
                    String::new()
                } else {
                    format!(" in {what}")
                };
                return Err(StoreError::invalid(
                    header,
                    "data",
                    format!(
                        "gzip stream is corrupt{in_}: expected the gzip signature 1f 8b{at}, \
                         found {:02x} {:02x}",
                        magic[0], magic[1]
                    ),
                ));
            }
            // Deflate inflates at most MAX_DEFLATE_RATIO-fold: a header
            // claiming more than the stream can hold is refused now rather
            // than after decompressing all of it.
            let compressed = len.saturating_sub(start);
            let most = compressed.saturating_mul(MAX_DEFLATE_RATIO);
            let skip = plan.byte_skip.max(0) as u64;
            if per_file.saturating_add(skip) > most {
                let skipped = if skip > 0 {
                    format!(" plus {skip} (byte skip)")
                } else {
                    String::new()
                };
                return Err(StoreError::invalid(
                    header,
                    "data",
                    format!(
                        "{what} holds a gzip stream of {compressed} bytes{at}{after}, which \
                         inflates to at most {most} bytes, but sizes × type need \
                         {per_file}{per}{skipped}"
                    ),
                ));
            }
            Ok(start)
        }
    }
}

// ---------------------------------------------------------------------------
// Reading

impl VolumeSource for NrrdSource {
    fn meta(&self) -> &SourceMeta {
        &self.meta
    }

    fn read_region(
        &self,
        c: usize,
        z: Range<u64>,
        y: Range<u64>,
        x: Range<u64>,
        out: &mut [u8],
    ) -> Result<()> {
        check_region(&self.meta, c, &z, &y, &x, out);
        if out.is_empty() {
            return Ok(());
        }
        let size = self.meta.dtype.size();
        self.flip.read(z, y, x, out, size, |z, y, x, out| {
            self.read_stored(c, &z, &y, &x, out)
        })
    }
}

impl NrrdSource {
    /// Read a region as the file stores it (not reversed).
    fn read_stored(
        &self,
        c: usize,
        z: &Range<u64>,
        y: &Range<u64>,
        x: &Range<u64>,
        out: &mut [u8],
    ) -> Result<()> {
        let rows = Rows::new(self, c, z, y, x);
        match self.encoding {
            Encoding::Raw => {
                let mut handle: Option<(usize, File)> = None;
                rows.copy(out, &mut |off, buf| self.raw_read(off, buf, &mut handle))?;
            }
            Encoding::Gzip => self.gzip_region(&rows, c, out)?,
        }
        if self.big_endian {
            swap_bytes_in_place(out, self.meta.dtype.size());
        }
        Ok(())
    }
}

/// The rows (z, y) of a region and where each lies in the payload.
struct Rows {
    z: Range<u64>,
    y: Range<u64>,
    /// Payload offset of row (z, y) is `base + z * dz + y * dy` bytes.
    base: u64,
    dz: u64,
    dy: u64,
    /// Payload bytes of one row (all channels when interleaved).
    row_len: usize,
    /// Output bytes of one row.
    out_len: usize,
    /// Element size.
    size: usize,
    /// Channels per pixel in the payload (1 unless interleaved).
    px: usize,
    c: usize,
}

impl Rows {
    fn new(s: &NrrdSource, c: usize, z: &Range<u64>, y: &Range<u64>, x: &Range<u64>) -> Rows {
        let size = s.meta.dtype.size();
        let l = &s.layout;
        let px = if l.interleaved { s.meta.channels } else { 1 };
        let chan = if l.interleaved {
            0
        } else {
            c as u64 * l.channel_stride
        };
        let w = (x.end - x.start) as usize;
        let sz = size as u64;
        Rows {
            z: z.clone(),
            y: y.clone(),
            base: (x.start * l.stride[2] + chan) * sz,
            dz: l.stride[0] * sz,
            dy: l.stride[1] * sz,
            row_len: w * px * size,
            out_len: w * size,
            size,
            px,
            c,
        }
    }

    fn offset(&self, z: u64, y: u64) -> u64 {
        self.base + z * self.dz + y * self.dy
    }

    /// Payload byte range spanned by all rows.
    fn span(&self) -> Range<u64> {
        let first = self.offset(self.z.start, self.y.start);
        let last = self.offset(self.z.end - 1, self.y.end - 1) + self.row_len as u64;
        first..last
    }

    /// Fill `out` using `read(payload offset, buf)`, merging rows that are
    /// adjacent in the payload into one read.
    fn copy(
        &self,
        out: &mut [u8],
        read: &mut dyn FnMut(u64, &mut [u8]) -> Result<()>,
    ) -> Result<()> {
        let max_rows = if self.px == 1 {
            usize::MAX
        } else {
            (CHUNK_BYTES / self.row_len).max(1)
        };
        let mut tmp = Vec::new();
        // Pending run: payload offset, first row index, number of rows.
        let mut run: Option<(u64, usize, usize)> = None;
        let mut k = 0usize;
        for zz in self.z.clone() {
            for yy in self.y.clone() {
                let off = self.offset(zz, yy);
                match run {
                    Some((o, f, n)) if n < max_rows && o + (n * self.row_len) as u64 == off => {
                        run = Some((o, f, n + 1));
                    }
                    _ => {
                        if let Some(r) = run {
                            self.flush(r, out, &mut tmp, read)?;
                        }
                        run = Some((off, k, 1));
                    }
                }
                k += 1;
            }
        }
        if let Some(r) = run {
            self.flush(r, out, &mut tmp, read)?;
        }
        Ok(())
    }

    fn flush(
        &self,
        (off, first, n): (u64, usize, usize),
        out: &mut [u8],
        tmp: &mut Vec<u8>,
        read: &mut dyn FnMut(u64, &mut [u8]) -> Result<()>,
    ) -> Result<()> {
        let dst = &mut out[first * self.out_len..(first + n) * self.out_len];
        if self.px == 1 {
            return read(off, dst);
        }
        tmp.resize(n * self.row_len, 0);
        read(off, tmp)?;
        let (s, px, c) = (self.size, self.px, self.c);
        for (o, t) in dst.chunks_exact_mut(s).zip(tmp.chunks_exact(s * px)) {
            o.copy_from_slice(&t[c * s..(c + 1) * s]);
        }
        Ok(())
    }
}

impl NrrdSource {
    /// Read payload bytes `off..off + buf.len()` of raw data.
    fn raw_read(&self, off: u64, buf: &mut [u8], handle: &mut Option<(usize, File)>) -> Result<()> {
        let mut off = off;
        let mut done = 0;
        while done < buf.len() {
            let k = (off / self.per_file) as usize;
            let local = off % self.per_file;
            let n = ((self.per_file - local) as usize).min(buf.len() - done);
            let df = &self.files[k];
            let piece = &mut buf[done..done + n];
            let at = df.start + local;
            let res = match &self.raw_file {
                Some(f) => read_full_at(f, piece, at),
                None => {
                    let h = match handle.take() {
                        Some(h) if h.0 == k => handle.insert(h),
                        _ => {
                            let f = File::open(&df.path)
                                .map_err(|e| data_file_error(&self.meta.path, &df.path, e))?;
                            handle.insert((k, f))
                        }
                    };
                    read_full_at(&h.1, piece, at)
                }
            };
            let got = res.map_err(|e| {
                if self.attached {
                    StoreError::io(&self.meta.path, e)
                } else {
                    data_file_error(&self.meta.path, &df.path, e)
                }
            })?;
            if got < n {
                // The size was checked at open: the file shrank since.
                let msg = ends_early(at + got as u64, df.start + self.per_file);
                return Err(if self.attached {
                    StoreError::invalid(&self.meta.path, "data", msg)
                } else {
                    StoreError::invalid(
                        &df.path,
                        "data",
                        format!("{msg} (data file named in {})", self.meta.path.display()),
                    )
                });
            }
            done += n;
            off += n as u64;
        }
        Ok(())
    }

    fn gzip_region(&self, rows: &Rows, c: usize, out: &mut [u8]) -> Result<()> {
        let slot = c % self.gz.len();
        let mut guard = self.gz[slot].lock().unwrap_or_else(PoisonError::into_inner);
        let GzState { cursor, cache } = &mut *guard;
        let result = self.gzip_region_locked(rows, out, cursor, cache);
        if result.is_err() {
            *cursor = None;
            *cache = None;
        }
        result
    }

    fn gzip_region_locked(
        &self,
        rows: &Rows,
        out: &mut [u8],
        cursor: &mut Option<GzCursor>,
        cache: &mut Option<(u64, Vec<u8>)>,
    ) -> Result<()> {
        let span = rows.span();
        if let Some((start, data)) = cache.as_ref() {
            if *start <= span.start && span.end <= start + data.len() as u64 {
                return rows.copy(out, &mut |off, buf| {
                    let i = (off - start) as usize;
                    buf.copy_from_slice(&data[i..i + buf.len()]);
                    Ok(())
                });
            }
        }
        *cache = None;
        // Interleaved channels: keep the decompressed span for the other
        // channels, as long as it is not much larger than what they read.
        let span_len = span.end - span.start;
        if self.layout.interleaved && span_len <= 2 * out.len() as u64 * self.meta.channels as u64 {
            let mut data = vec![0u8; span_len as usize];
            self.gz_read(cursor, span.start, &mut data)?;
            let start = span.start;
            rows.copy(out, &mut |off, buf| {
                let i = (off - start) as usize;
                buf.copy_from_slice(&data[i..i + buf.len()]);
                Ok(())
            })?;
            *cache = Some((start, data));
            return Ok(());
        }
        rows.copy(out, &mut |off, buf| self.gz_read(cursor, off, buf))
    }

    /// Read payload bytes `off..off + buf.len()` of gzip data through the
    /// cursor, restarting a file's stream only when `off` lies behind it.
    fn gz_read(&self, cursor: &mut Option<GzCursor>, off: u64, buf: &mut [u8]) -> Result<()> {
        let mut off = off;
        let mut done = 0;
        while done < buf.len() {
            let k = (off / self.per_file) as usize;
            let local = off % self.per_file;
            let n = ((self.per_file - local) as usize).min(buf.len() - done);
            let target = self.gz_skip + local;
            let cur = match cursor.take() {
                Some(cur) if cur.file == k && cur.pos <= target => cursor.insert(cur),
                _ => cursor.insert(self.gz_open(k)?),
            };
            if cur.pos < target {
                let mut scratch = vec![0u8; GZ_BUF_BYTES];
                while cur.pos < target {
                    let m = ((target - cur.pos) as usize).min(scratch.len());
                    self.gz_fill(cur, &mut scratch[..m])?;
                }
            }
            self.gz_fill(cur, &mut buf[done..done + n])?;
            done += n;
            off += n as u64;
            if cur.pos == self.gz_skip + self.per_file {
                self.gz_drain(cur)?;
            }
        }
        Ok(())
    }

    /// After a file's last payload byte: decompress to the end of its
    /// stream, where gzip checks its CRC and length (a flipped bit in the
    /// data is caught only there).
    fn gz_drain(&self, cur: &mut GzCursor) -> Result<()> {
        let mut scratch = vec![0u8; GZ_BUF_BYTES];
        loop {
            match cur.dec.read(&mut scratch) {
                Ok(0) => return Ok(()),
                Ok(_) => {}
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(e) => {
                    return Err(StoreError::invalid(
                        &self.meta.path,
                        "data",
                        format!(
                            "gzip stream{} fails its check at the end: {e}",
                            self.where_(cur.file)
                        ),
                    ))
                }
            }
        }
    }

    fn gz_open(&self, k: usize) -> Result<GzCursor> {
        let df = &self.files[k];
        let io_err = |e| {
            if self.attached {
                StoreError::io(&df.path, e)
            } else {
                data_file_error(&self.meta.path, &df.path, e)
            }
        };
        let mut f = File::open(&df.path).map_err(io_err)?;
        #[cfg(test)]
        self.gz_opens
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        f.seek(SeekFrom::Start(df.start)).map_err(io_err)?;
        Ok(GzCursor {
            file: k,
            pos: 0,
            dec: MultiGzDecoder::new(BufReader::with_capacity(GZ_BUF_BYTES, f)),
        })
    }

    /// Decompress exactly `buf.len()` bytes.
    fn gz_fill(&self, cur: &mut GzCursor, buf: &mut [u8]) -> Result<()> {
        let mut done = 0;
        while done < buf.len() {
            match cur.dec.read(&mut buf[done..]) {
                Ok(0) => {
                    let got = cur.pos.saturating_sub(self.gz_skip);
                    let skip = if self.gz_skip > 0 {
                        format!(" (after skipping {} bytes for byte skip)", self.gz_skip)
                    } else {
                        String::new()
                    };
                    return Err(StoreError::invalid(
                        &self.meta.path,
                        "data",
                        format!(
                            "gzip stream{} ends after {got} bytes{skip} but sizes × type need {}{} \
                             (truncated file?)",
                            self.where_(cur.file),
                            self.per_file,
                            if self.files.len() > 1 { " per file" } else { "" },
                        ),
                    ));
                }
                Ok(n) => {
                    done += n;
                    cur.pos += n as u64;
                }
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(e) if matches!(e.kind(), ErrorKind::InvalidInput | ErrorKind::InvalidData) => {
                    return Err(StoreError::invalid(
                        &self.meta.path,
                        "data",
                        format!("gzip stream is corrupt{}: {e}", self.where_(cur.file)),
                    ));
                }
                Err(e) if e.kind() == ErrorKind::UnexpectedEof => {
                    return Err(StoreError::invalid(
                        &self.meta.path,
                        "data",
                        format!(
                            "gzip stream{} is truncated: {e} (after {} bytes)",
                            self.where_(cur.file),
                            cur.pos.saturating_sub(self.gz_skip)
                        ),
                    ));
                }
                Err(e) => {
                    let df = &self.files[cur.file];
                    return Err(if self.attached {
                        StoreError::io(&df.path, e)
                    } else {
                        data_file_error(&self.meta.path, &df.path, e)
                    });
                }
            }
        }
        Ok(())
    }
}
