//! A `process` job whose cancel flag (Ctrl-C) is raised after its
//! labelling pass publishes nothing: the store is as it was. The flag used
//! to be looked at only while voxels were being labelled or written, so a
//! signal during the final numbering, the statistics or the publishing
//! let the job publish and succeed.

use brickyard_run::process::{run, Caller, Phases, ProcessArgs};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress, Progress};
use brickyard_store::generate::{Kind, Procedural};
use std::sync::atomic::{AtomicBool, Ordering};

const CALLER: Caller = Caller {
    flag: "--",
    convert: "convert",
    remote: "",
    overwrite: "pass --overwrite",
    again: "command",
};

/// Raises the cancel flag when the phase named finishes.
struct CancelAfter<'a> {
    labelling: bool,
    cancel: &'a AtomicBool,
}

impl Phases for CancelAfter<'_> {
    fn labelling(&self) -> &dyn Progress {
        &NoProgress
    }
    fn writing(&self) -> &dyn Progress {
        &NoProgress
    }
    fn done(&self, labelling: bool) {
        if labelling == self.labelling {
            self.cancel.store(true, Ordering::SeqCst);
        }
    }
}

#[test]
fn a_cancel_after_labelling_or_writing_publishes_nothing() {
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("m.ome.zarr");
    let src = Procedural::new(Kind::Mandelbulb, [40, 40, 40], brickyard_core::DType::U8);
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let job = |out: &str| ProcessArgs {
        store: store.clone(),
        pipeline: "threshold(100)|label(6)".into(),
        out: out.into(),
        memory: 64 << 20,
        level: 0,
        channel: 0,
        stats: None,
        overwrite: false,
        backend: "cpu".into(),
        quiet: true,
    };
    for labelling in [true, false] {
        let cancel = AtomicBool::new(false);
        let phases = CancelAfter {
            labelling,
            cancel: &cancel,
        };
        let e = match run(&job("x"), &CALLER, &phases, &cancel) {
            Ok(_) => panic!("cancelled after labelling={labelling}, yet published"),
            Err(e) => format!("{e:#}"),
        };
        assert!(e.contains("nothing was published"), "{e}");
        let left: Vec<_> = std::fs::read_dir(store.join("labels"))
            .map(|r| r.map(|e| e.unwrap().file_name()).collect())
            .unwrap_or_default();
        assert!(left.is_empty(), "labelling={labelling}: left {left:?}");
    }
    // Not cancelled, the same job publishes.
    let cancel = AtomicBool::new(false);
    let phases = CancelAfter {
        labelling: true,
        cancel: &AtomicBool::new(false),
    };
    let r = run(&job("x"), &CALLER, &phases, &cancel).unwrap();
    assert!(r.labels.unwrap() > 0);
    assert!(store.join("labels/x/zarr.json").exists());
}
