//! A render run as `brickyard render` drives it: the backend (CPU or
//! device), the frame loop, the memory split, default data windows and live
//! derived channels; and a processing job as `brickyard process` runs it
//! (`process`). Shared by the CLI and the Python bindings, so that both
//! draw the same image of the same view and write the same results.

/// `println!` that never fails: standard output closed early (`| head`)
/// drops the text instead of ending the run, so images and stores are
/// still written.
#[macro_export]
macro_rules! outln {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stdout(), $($t)*);
    }};
}

/// [`outln!`] without the line break.
#[macro_export]
macro_rules! out {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let _ = write!(std::io::stdout(), $($t)*);
    }};
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
