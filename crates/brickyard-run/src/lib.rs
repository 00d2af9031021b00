//! A render run as `brickyard render` drives it: the backend (CPU or
//! device), the frame loop, the memory split, default data windows and live
//! derived channels; and a processing job as `brickyard process` runs it
//! (`process`). Shared by the CLI and the Python bindings, so that both
//! draw the same image of the same view and write the same results.

/// `println!` that does not end the run when standard output fails: a
/// pipe closed early (`| head`) drops the text, so images and stores are
/// still written; another failure (a full disk under `> file`) is kept for
/// [`out_error`], so the command ends with an error instead of a
/// truncated file and status 0.
#[macro_export]
macro_rules! outln {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        $crate::note_out(writeln!(std::io::stdout(), $($t)*));
    }};
}

/// [`outln!`] without the line break.
#[macro_export]
macro_rules! out {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        $crate::note_out(write!(std::io::stdout(), $($t)*));
    }};
}

static OUT_ERROR: std::sync::OnceLock<String> = std::sync::OnceLock::new();

/// Keep the first failure of a write to standard output other than a
/// closed pipe ([`outln!`]).
pub fn note_out(r: std::io::Result<()>) {
    if let Err(e) = r {
        if e.kind() != std::io::ErrorKind::BrokenPipe {
            let _ = OUT_ERROR.set(e.to_string());
        }
    }
}

/// Flush standard output and say whether any write to it failed (other
/// than a closed pipe): what was printed is then incomplete.
pub fn out_error() -> Option<String> {
    use std::io::Write as _;
    note_out(std::io::stdout().flush());
    OUT_ERROR.get().cloned()
}

/// Whether a new file can be made in the folder of `file` (read-only
/// mounts and file systems that take none are found before the work, not
/// after it): a file made there and removed. The folder and the error
/// where not.
pub fn can_create_beside(
    file: &std::path::Path,
) -> Result<(), (std::path::PathBuf, std::io::Error)> {
    let dir = file
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(std::path::Path::new("."));
    let name = file.file_name().unwrap_or_default().to_string_lossy();
    for k in 0..100 {
        let probe = dir.join(format!(".{name}.{}.{k}.probe", std::process::id()));
        match std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&probe)
        {
            Ok(_) => {
                let _ = std::fs::remove_file(&probe);
                return Ok(());
            }
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err((dir.to_path_buf(), e)),
        }
    }
    Ok(())
}

pub mod backend;
pub mod derive;
pub mod frames;
pub mod label_stats;
pub mod labels;
pub mod memory;
pub mod process;
pub mod render;
pub mod share;
pub mod window;
