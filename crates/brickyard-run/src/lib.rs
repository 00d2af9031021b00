//! A render run as `brickyard render` drives it: the backend (CPU or
//! device), the frame loop, the memory split, default data windows and live
//! derived channels; and a processing job as `brickyard process` runs it
//! (`process`). Shared by the CLI and the Python bindings, so that both
//! draw the same image of the same view and write the same results.

pub mod backend;
pub mod derive;
pub mod frames;
pub mod memory;
pub mod process;
pub mod render;
pub mod share;
pub mod window;
