//! A render run as `brickyard render` drives it: the backend (CPU or
//! device), the frame loop, the memory split, default data windows and live
//! derived channels. Shared by the CLI and the Python bindings, so that both
//! draw the same image of the same view.

pub mod backend;
pub mod derive;
pub mod frames;
pub mod memory;
pub mod render;
pub mod window;
