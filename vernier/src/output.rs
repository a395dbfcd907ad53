//! Checked file output: every byte written, flushed and synced, every failure reported
//! (a full disk is an error, never a silently truncated file).

use std::io::Write;
use std::path::Path;

/// Writes `bytes` to `path` (created or truncated), then flushes and syncs it to the device,
/// so that a full disk (ENOSPC) or an I/O error surfaces here rather than when the file is
/// closed, where it would be lost. Devices that cannot be synced (pipes, `/dev/null`) are
/// fine.
pub fn write_file(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let mut file = std::fs::File::create(path)?;
    file.write_all(bytes)?;
    file.flush()?;
    sync(&file)
}

/// `sync_all`, ignoring the errors of files that cannot be synced (character devices,
/// pipes): their data is already handed over.
pub fn sync(file: &std::fs::File) -> std::io::Result<()> {
    match file.sync_all() {
        Err(e)
            if matches!(
                e.kind(),
                std::io::ErrorKind::InvalidInput | std::io::ErrorKind::Unsupported
            ) =>
        {
            Ok(())
        }
        other => other,
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_full_device_is_an_error() {
        let full = std::path::Path::new("/dev/full");
        if full.exists() {
            let e = super::write_file(full, &[0u8; 100]).unwrap_err();
            assert_eq!(e.raw_os_error(), Some(28), "{e}");
        }
    }
}
