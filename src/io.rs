//! Small file helpers: atomic writes (temp file + rename) so an interrupted run never leaves a
//! half-written output, and checked reads that refuse inputs which would block or never end (a
//! FIFO, a device such as `/dev/zero`) or exhaust memory (an oversized text file).

use std::io::Read;
use std::path::{Path, PathBuf};

/// Largest parameter file read (JSON): real ones are a few KiB; the cap keeps `/dev/zero`-like or
/// runaway inputs from filling memory.
pub const MAX_PARAM_FILE_BYTES: u64 = 16 << 20;

/// Largest small text input read whole (recipes, training configs, dataset manifests and label
/// lists): generous for a million-line `labels.jsonl`, far below the machine's memory.
pub const MAX_TEXT_FILE_BYTES: u64 = 1 << 30;

/// Temporary sibling path used while writing `path`.
pub fn temp_path(path: &Path) -> PathBuf {
    let name = path.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
    let ext = path.extension().map(|e| e.to_string_lossy().to_string()).unwrap_or_default();
    // Keep the extension last: some encoders pick the format from it.
    path.with_file_name(format!(".{name}.{}.tmp.{ext}", std::process::id()))
}

fn create_parent(path: &Path) -> std::io::Result<()> {
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => std::fs::create_dir_all(dir),
        _ => Ok(()),
    }
}

/// Write `bytes` to `path` atomically.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    create_parent(path)?;
    let tmp = temp_path(path);
    std::fs::write(&tmp, bytes)?;
    std::fs::rename(&tmp, path)
}

/// Write several files as one unit: every file goes to its temporary name first, and only when all
/// of them are written are they renamed into place. A failure while writing (an unwritable folder,
/// a full disk) removes the temporaries and leaves every destination untouched, so a command never
/// leaves half of its outputs behind (e.g. a PNG without the EXR that was asked for).
pub fn write_all_atomic(files: &[(&Path, &[u8])]) -> std::io::Result<()> {
    let mut written: Vec<PathBuf> = Vec::with_capacity(files.len());
    let cleanup = |written: &[PathBuf]| {
        for t in written {
            let _ = std::fs::remove_file(t);
        }
    };
    for (path, bytes) in files {
        let tmp = temp_path(path);
        if let Err(e) = create_parent(path).and_then(|_| std::fs::write(&tmp, bytes)) {
            cleanup(&written);
            let _ = std::fs::remove_file(&tmp);
            return Err(std::io::Error::new(e.kind(), format!("{}: {e}", path.display())));
        }
        written.push(tmp);
    }
    for (k, (path, _)) in files.iter().enumerate() {
        if let Err(e) = std::fs::rename(&written[k], path) {
            cleanup(&written[k..]);
            return Err(std::io::Error::new(e.kind(), format!("{}: {e}", path.display())));
        }
    }
    Ok(())
}

/// Metadata of `path` if it is a regular file (symbolic links followed). A FIFO would block the
/// reader forever and a device (`/dev/zero`) never ends, so inputs are checked before they are
/// opened; a folder is refused with the same clear message.
pub fn check_regular_file(path: &Path) -> std::io::Result<std::fs::Metadata> {
    let meta = std::fs::metadata(path)?;
    if !meta.is_file() {
        let what = if meta.is_dir() { "a folder" } else { "not a regular file (a FIFO, socket or device)" };
        return Err(std::io::Error::new(std::io::ErrorKind::InvalidInput, format!("{} is {what}", path.display())));
    }
    Ok(meta)
}

/// Read a regular file of at most `max_bytes` bytes (see [`check_regular_file`]); a larger file is
/// refused before it is read, and the read itself stops at the cap in case the file grows.
pub fn read_capped(path: &Path, max_bytes: u64) -> std::io::Result<Vec<u8>> {
    let meta = check_regular_file(path)?;
    let too_big = || {
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("{} is larger than the {} MiB allowed for this kind of file", path.display(), max_bytes >> 20),
        )
    };
    if meta.len() > max_bytes {
        return Err(too_big());
    }
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    std::fs::File::open(path)?.take(max_bytes + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > max_bytes {
        return Err(too_big());
    }
    Ok(bytes)
}

/// [`read_capped`] as UTF-8 text.
pub fn read_text_capped(path: &Path, max_bytes: u64) -> std::io::Result<String> {
    String::from_utf8(read_capped(path, max_bytes)?).map_err(|_| {
        std::io::Error::new(std::io::ErrorKind::InvalidData, format!("{} is not UTF-8 text", path.display()))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn capped_reads_refuse_folders_big_files_and_devices() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("a.txt");
        std::fs::write(&f, "hello").unwrap();
        assert_eq!(read_text_capped(&f, 5).unwrap(), "hello");
        let e = read_capped(&f, 4).unwrap_err().to_string();
        assert!(e.contains("larger than"), "{e}");
        let e = read_capped(dir.path(), 100).unwrap_err().to_string();
        assert!(e.contains("a folder"), "{e}");
        if Path::new("/dev/zero").exists() {
            let e = read_capped(Path::new("/dev/zero"), 100).unwrap_err().to_string();
            assert!(e.contains("not a regular file"), "{e}");
        }
        std::fs::write(&f, [0xff, 0xfe]).unwrap();
        assert!(read_text_capped(&f, 100).unwrap_err().to_string().contains("UTF-8"));
    }

    #[test]
    fn all_or_nothing_writes() {
        let dir = tempfile::tempdir().unwrap();
        let a = dir.path().join("a.bin");
        let b = dir.path().join("sub/b.bin");
        write_all_atomic(&[(&a, b"1"), (&b, b"2")]).unwrap();
        assert_eq!(std::fs::read(&b).unwrap(), b"2");
        // The second destination's folder is a file: nothing is replaced, no temporary is left.
        let blocker = dir.path().join("blocker");
        std::fs::write(&blocker, b"x").unwrap();
        let c = blocker.join("c.bin");
        assert!(write_all_atomic(&[(&a, b"new"), (&c, b"3")]).is_err());
        assert_eq!(std::fs::read(&a).unwrap(), b"1");
        let names: Vec<String> =
            std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into()).collect();
        assert!(names.iter().all(|n| !n.contains(".tmp")), "{names:?}");
    }
}
