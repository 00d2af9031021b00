//! `brickyard info --check`: a clean store passes with exit status 0; each
//! kind of damage (bytes flipped inside a chunk, a truncated shard, a broken
//! index CRC, an index entry past the end of the file, a chunk that decodes
//! to the wrong length, a chunk or shard missing where the statistics say
//! there is data, damaged statistics, an unreadable shard) is listed with
//! its shard file and a non-zero exit status, while what Zarr allows (a
//! missing shard where nothing says there is data) passes.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_brickyard"))
        .args(args)
        .output()
        .unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A 40³ u8 Mandelbulb store: bricks of 8³ in shards of 16³, so each shard
/// file holds up to 2×2×2 chunks and ends with an index of 8 entries and
/// its CRC32C.
fn clean_store(dir: &Path) -> PathBuf {
    let store = dir.join("clean.ome.zarr");
    let o = run(&[
        "generate",
        "mandelbulb",
        s(&store),
        "--size",
        "40",
        "--quiet",
        "--brick",
        "8",
        "--shard",
        "16",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    store
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let p = e.path();
        if p.is_dir() {
            copy_dir(&p, &to.join(e.file_name()));
        } else {
            std::fs::copy(&p, to.join(e.file_name())).unwrap();
        }
    }
}

/// `info --check --json`: the exit status and the `check` object.
fn check(store: &Path) -> (Option<i32>, serde_json::Value, String) {
    let o = run(&["info", s(store), "--check", "--json"]);
    let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(!stderr.contains("panicked"), "{stderr}");
    let v: serde_json::Value = serde_json::from_slice(&o.stdout)
        .unwrap_or_else(|e| panic!("{e}: {}\n{stderr}", String::from_utf8_lossy(&o.stdout)));
    (o.status.code(), v["check"].clone(), stderr)
}

const N: usize = 8; // chunks per shard
const INDEX: usize = N * 16 + 4;

/// The index entries `(offset, length)` of a shard file.
fn index(path: &Path) -> Vec<(u64, u64)> {
    let b = std::fs::read(path).unwrap();
    let ix = &b[b.len() - INDEX..];
    let crc = u32::from_le_bytes(ix[N * 16..].try_into().unwrap());
    assert_eq!(crc, crc32c::crc32c(&ix[..N * 16]), "{}", path.display());
    (0..N)
        .map(|j| {
            let e = |k: usize| u64::from_le_bytes(ix[16 * j + 8 * k..][..8].try_into().unwrap());
            (e(0), e(1))
        })
        .collect()
}

/// Replace the index of a shard file (with a correct CRC), keeping its data
/// and appending `extra` bytes to the data first.
fn rewrite_index(path: &Path, extra: &[u8], entries: &[(u64, u64)]) {
    let b = std::fs::read(path).unwrap();
    let mut out = b[..b.len() - INDEX].to_vec();
    out.extend_from_slice(extra);
    let mut ix = vec![];
    for &(o, l) in entries {
        ix.extend_from_slice(&o.to_le_bytes());
        ix.extend_from_slice(&l.to_le_bytes());
    }
    let crc = crc32c::crc32c(&ix);
    out.extend_from_slice(&ix);
    out.extend_from_slice(&crc.to_le_bytes());
    std::fs::write(path, out).unwrap();
}

/// A level-0 shard whose eight chunks are all stored, its shard index and
/// its entries.
fn full_shard(store: &Path) -> (PathBuf, [u64; 3], Vec<(u64, u64)>) {
    for z in 0..3 {
        for y in 0..3 {
            for x in 0..3 {
                let p = store.join(format!("0/c/{z}/{y}/{x}"));
                if p.exists() {
                    let e = index(&p);
                    if e.iter().all(|&(o, _)| o != u64::MAX) {
                        return (p, [z, y, x], e);
                    }
                }
            }
        }
    }
    panic!("no level-0 shard with all eight chunks stored");
}

/// The chunk (brick) index of entry `j` of shard `sh`.
fn chunk_of(sh: [u64; 3], j: usize) -> Vec<u64> {
    let l = [j as u64 / 4, j as u64 / 2 % 2, j as u64 % 2];
    (0..3).map(|a| sh[a] * 2 + l[a]).collect()
}

/// Exit status 1, and a problem on `path` (and `chunk`, when given) whose
/// message contains each of `words`.
#[track_caller]
fn reported(
    what: &str,
    (code, check, stderr): &(Option<i32>, serde_json::Value, String),
    path: &Path,
    chunk: Option<&[u64]>,
    words: &[&str],
) {
    let problems = check["problems"].as_array().expect("problems");
    let hit = problems.iter().find(|p| {
        Path::new(p["path"].as_str().unwrap()) == path
            && chunk.is_none_or(|c| p["chunk"] == serde_json::json!(c))
    });
    let Some(hit) = hit else {
        panic!(
            "{what}: no problem reported on {} chunk {chunk:?}: {problems:#?}\n{stderr}",
            path.display()
        );
    };
    let msg = hit["error"].as_str().unwrap();
    eprintln!("{what}: {msg}");
    for w in words {
        assert!(msg.contains(w), "{what}: {msg:?} should mention {w:?}");
    }
    assert_eq!(*code, Some(1), "{what}: exit status");
}

#[test]
fn info_check_passes_clean_stores() {
    let d = tempfile::tempdir().unwrap();
    let store = clean_store(d.path());
    let (code, c, stderr) = check(&store);
    assert_eq!(code, Some(0), "{c:#}\n{stderr}");
    assert_eq!(c["problems"], serde_json::json!([]));
    // 5³ + 3³ + 2³ + 1 bricks in the levels (40, 20, 10, 5 voxels), and
    // one statistics chunk per level.
    let chunks = c["chunks"].as_u64().unwrap();
    assert_eq!(chunks, 125 + 27 + 8 + 1 + 4, "{c:#}");
    let (stored, absent) = (c["stored"].as_u64().unwrap(), c["absent"].as_u64().unwrap());
    assert_eq!(stored + absent, chunks);
    assert!(stored > 100 && absent > 0, "{c:#}");
    assert_eq!(c["arrays"], 8);
    // The text form says the same.
    let o = run(&["info", s(&store), "--check"]);
    assert!(o.status.success());
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(
        text.contains(&format!("check: {chunks} chunks in 8 arrays")) && text.contains("; 0 bad"),
        "{text}"
    );
    assert!(!text.contains("BAD"), "{text}");
    // One level of it, given as a store: described, and said to be a level
    // of the image above (it was called a foreign store).
    let o = run(&["info", s(&store.join("1"))]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{text}");
    assert!(
        text.contains("one level of an OME-Zarr image")
            && text.contains(&format!(
                "level 1 of 4 levels of the image {}",
                store.display()
            ))
            && !text.contains("foreign"),
        "{text}"
    );

    // Two channels (4-D arrays), zstd: the statistics still match.
    let raw = d.path().join("one.raw");
    let o = run(&[
        "generate",
        "marschner-lobb",
        s(&raw),
        "--size",
        "24x20x18",
        "--quiet",
    ]);
    assert!(o.status.success());
    let one = std::fs::read(&raw).unwrap();
    let two = d.path().join("two.raw");
    std::fs::write(
        &two,
        [one.clone(), one.iter().map(|v| v / 2).collect()].concat(),
    )
    .unwrap();
    let store2 = d.path().join("two.ome.zarr");
    let o = run(&[
        "convert",
        s(&two),
        s(&store2),
        "--dims",
        "24x20x18",
        "--dtype",
        "u8",
        "--channels",
        "2",
        "--brick",
        "8",
        "--shard",
        "16",
        "--compression",
        "zstd",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (code, c, stderr) = check(&store2);
    assert_eq!(code, Some(0), "{c:#}\n{stderr}");
    assert!(c["stored"].as_u64().unwrap() > 20, "{c:#}");

    // Without statistics nothing says where data should be: a missing
    // shard is the fill value, as Zarr has it.
    let bare = d.path().join("bare.ome.zarr");
    copy_dir(&store, &bare);
    std::fs::remove_dir_all(bare.join("_brickyard")).unwrap();
    let (p, _, _) = full_shard(&bare);
    std::fs::remove_file(&p).unwrap();
    let (code, c, _) = check(&bare);
    assert_eq!(code, Some(0), "{c:#}");
    assert_eq!(c["arrays"], 4);
    assert!(c["absent"].as_u64().unwrap() >= 8);
}

#[test]
fn info_check_lists_damaged_chunks_and_shards() {
    let d = tempfile::tempdir().unwrap();
    let clean = clean_store(d.path());
    let mut n = 0;
    let mut copy = || {
        n += 1;
        let p = d.path().join(format!("damaged-{n}.ome.zarr"));
        copy_dir(&clean, &p);
        p
    };

    // Bytes flipped inside a chunk's compressed data (past the 16-byte
    // blosc header).
    let store = copy();
    let (path, sh, e) = full_shard(&store);
    let (j, &(off, len)) = e.iter().enumerate().max_by_key(|(_, e)| e.1).unwrap();
    assert!(len > 64, "{len}");
    let mut b = std::fs::read(&path).unwrap();
    for x in &mut b[off as usize + 16..(off + len) as usize] {
        *x ^= 0x5a;
    }
    std::fs::write(&path, b).unwrap();
    reported(
        "flipped bytes",
        &check(&store),
        &path,
        Some(&chunk_of(sh, j)),
        &[],
    );

    // A shard cut in half: its index is gone (what is now at the end fails
    // the CRC), and a shard shorter than an index.
    let store = copy();
    let (path, _, _) = full_shard(&store);
    let f = std::fs::OpenOptions::new().write(true).open(&path).unwrap();
    let len = f.metadata().unwrap().len();
    f.set_len(len / 2).unwrap();
    drop(f);
    reported("truncated", &check(&store), &path, None, &["CRC32C"]);
    let f = std::fs::OpenOptions::new().write(true).open(&path).unwrap();
    f.set_len(100).unwrap();
    drop(f);
    reported(
        "truncated below the index",
        &check(&store),
        &path,
        None,
        &["fewer than its index"],
    );

    // The index CRC damaged.
    let store = copy();
    let (path, _, _) = full_shard(&store);
    let mut b = std::fs::read(&path).unwrap();
    *b.last_mut().unwrap() ^= 1;
    std::fs::write(&path, b).unwrap();
    reported(
        "index CRC",
        &check(&store),
        &path,
        None,
        &["CRC32C mismatch"],
    );

    // A chunk whose offset lies past the end of the file (valid CRC).
    let store = copy();
    let (path, sh, mut e) = full_shard(&store);
    let size = std::fs::metadata(&path).unwrap().len();
    e[3].0 = size + 1000;
    rewrite_index(&path, &[], &e);
    reported(
        "offset past the end",
        &check(&store),
        &path,
        Some(&chunk_of(sh, 3)),
        &["outside the shard's data"],
    );

    // A chunk that decodes to the wrong length: a valid blosc stream of 100
    // bytes where a brick has 512.
    let store = copy();
    let (path, sh, mut e) = full_shard(&store);
    let short = brickyard_store::codec::BrickEncoder::new(
        brickyard_store::Compression::Lz4,
        brickyard_core::DType::U8,
    )
    .encode(&[7u8; 100]);
    let data_end = std::fs::metadata(&path).unwrap().len() - INDEX as u64;
    e[5] = (data_end, short.len() as u64);
    rewrite_index(&path, &short, &e);
    reported(
        "wrong length",
        &check(&store),
        &path,
        Some(&chunk_of(sh, 5)),
        &["decode"],
    );

    // A chunk left out of the index, and a shard file removed, where the
    // statistics say there is data.
    let store = copy();
    let (path, sh, mut e) = full_shard(&store);
    e[6] = (u64::MAX, u64::MAX);
    rewrite_index(&path, &[], &e);
    reported(
        "absent chunk",
        &check(&store),
        &path,
        Some(&chunk_of(sh, 6)),
        &["absent from the shard index", "statistics"],
    );
    let store = copy();
    let (path, sh, _) = full_shard(&store);
    std::fs::remove_file(&path).unwrap();
    reported(
        "missing shard",
        &check(&store),
        &path,
        Some(&chunk_of(sh, 0)),
        &["missing", "statistics say 8 of its chunks"],
    );

    // Damaged statistics (zstd, unsharded).
    let store = copy();
    let path = store.join("_brickyard/stats/0/c/0/0/0/0/0");
    let mut b = std::fs::read(&path).unwrap();
    let mid = b.len() / 2;
    for x in &mut b[4..mid] {
        *x ^= 0xff;
    }
    std::fs::write(&path, b).unwrap();
    let r = check(&store);
    reported("statistics", &r, &path, None, &[]);
    assert!(
        r.1["problems"]
            .as_array()
            .unwrap()
            .iter()
            .any(|p| p["array"] == "statistics of level 0"),
        "{:#}",
        r.1
    );

    // A chunk of the statistics lost (they are written whole).
    let store = copy();
    let path = store.join("_brickyard/stats/0/c/0/0/0/0/0");
    std::fs::remove_file(&path).unwrap();
    reported(
        "missing statistics",
        &check(&store),
        &path,
        None,
        &["missing", "the statistics are written whole"],
    );

    // A shard nobody may read.
    let store = copy();
    let (path, _, _) = full_shard(&store);
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o000)).unwrap();
    if std::fs::File::open(&path).is_ok() {
        // Root (or CAP_DAC_OVERRIDE) reads it anyway: nothing to detect.
        eprintln!(
            "note: the permission case is not checked: this process can read a file with mode 000 (running as root)"
        );
    } else {
        reported(
            "unreadable",
            &check(&store),
            &path,
            None,
            &["cannot open", "ermission"],
        );
    }
    std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o644)).unwrap();

    // A FIFO where a shard belongs: opening it would wait for a writer.
    let store = copy();
    let (path, _, _) = full_shard(&store);
    std::fs::remove_file(&path).unwrap();
    assert!(Command::new("mkfifo")
        .arg(&path)
        .status()
        .unwrap()
        .success());
    let mut child = Command::new(env!("CARGO_BIN_EXE_brickyard"))
        .args(["info", s(&store), "--check", "--json"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = std::time::Instant::now();
    while child.try_wait().unwrap().is_none() {
        if t0.elapsed().as_secs() > 60 {
            child.kill().unwrap();
            panic!("info --check waits on a FIFO in place of a shard");
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let o = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).expect("JSON");
    reported(
        "fifo",
        &(o.status.code(), j["check"].clone(), stderr),
        &path,
        None,
        &["not a regular file"],
    );

    // Several problems at once are all listed, in the text form too.
    let store = copy();
    let (a, _, _) = full_shard(&store);
    let mut b = std::fs::read(&a).unwrap();
    *b.last_mut().unwrap() ^= 1;
    std::fs::write(&a, b).unwrap();
    let other = store.join("1/c/0/0/0");
    let mut b = std::fs::read(&other).unwrap();
    *b.last_mut().unwrap() ^= 1;
    std::fs::write(&other, b).unwrap();
    let o = run(&["info", s(&store), "--check"]);
    assert_eq!(o.status.code(), Some(1));
    let text = String::from_utf8_lossy(&o.stdout);
    let bad: Vec<&str> = text.lines().filter(|l| l.contains("BAD:")).collect();
    assert_eq!(bad.len(), 2, "{text}");
    assert!(
        bad[0].contains("level 0, shard") && bad[0].contains(s(&a)),
        "{text}"
    );
    assert!(
        bad[1].contains("level 1, shard") && bad[1].contains(s(&other)),
        "{text}"
    );
    assert!(text.contains("; 2 bad"), "{text}");
}

/// The images `process` writes into a store (`labels/NAME`,
/// `derived/NAME`) are checked with it: a truncated shard or damaged
/// metadata of a result makes the store's check fail, naming the image.
/// (They were left out: the store passed with exit 0.)
#[test]
fn info_check_covers_the_images_inside_a_store() {
    let d = tempfile::tempdir().unwrap();
    let store = clean_store(d.path());
    for (pipe, out) in [("gauss(1)", "g"), ("threshold(100)|label(6)", "cells")] {
        let o = run(&["process", s(&store), pipe, "--out", out, "--quiet"]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    let (code, j, _) = check(&store);
    assert_eq!(code, Some(0), "{j}");
    // Levels and statistics of the store and of both images.
    let arrays = j["arrays"].as_u64().unwrap();
    let mut alone = d.path().join("alone.ome.zarr");
    copy_dir(&store, &alone);
    std::fs::remove_dir_all(alone.join("labels")).unwrap();
    std::fs::remove_dir_all(alone.join("derived")).unwrap();
    let (_, j0, _) = check(&alone);
    assert!(arrays > j0["arrays"].as_u64().unwrap(), "{j}");
    // A truncated shard of the derived image.
    let bad = d.path().join("bad.ome.zarr");
    copy_dir(&store, &bad);
    let shard = bad.join("derived/g/0/c/0/0/0");
    let len = std::fs::metadata(&shard).unwrap().len();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&shard)
        .unwrap()
        .set_len(len / 3)
        .unwrap();
    let (code, j, _) = check(&bad);
    assert_eq!(code, Some(1), "{j}");
    let arrays_named = |j: &serde_json::Value| -> Vec<String> {
        j["problems"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p["array"].as_str().unwrap().to_string())
            .collect()
    };
    assert!(
        arrays_named(&j).iter().any(|a| a == "derived/g level 0"),
        "{j}"
    );
    // Damaged metadata of a level of the label image.
    alone = d.path().join("bad2.ome.zarr");
    copy_dir(&store, &alone);
    std::fs::write(alone.join("labels/cells/0/zarr.json"), "{\"zarr_for").unwrap();
    let (code, j, _) = check(&alone);
    assert_eq!(code, Some(1), "{j}");
    assert!(
        arrays_named(&j)
            .iter()
            .any(|a| a.starts_with("labels/cells")),
        "{j}"
    );
    // A shard of the label image gone: its statistics say it held labels
    // (the images' statistics were read but not used before).
    let lost = d.path().join("lost.ome.zarr");
    copy_dir(&store, &lost);
    let shard = lost.join("labels/cells/0/c/0/0/0");
    std::fs::remove_file(&shard).unwrap();
    let (code, j, _) = check(&lost);
    assert_eq!(code, Some(1), "{j}");
    assert!(
        j["problems"]
            .as_array()
            .unwrap()
            .iter()
            .any(|p| p["array"] == "labels/cells level 0"
                && p["error"].as_str().unwrap().contains("statistics")),
        "{j}"
    );
    // The label table `--only-labels` goes by: cut short, or not a table.
    let table = store.join("labels/cells/_brickyard/labels.csv");
    let whole = std::fs::read_to_string(&table).unwrap();
    let rows = whole.lines().count() - 1;
    assert!(rows > 3, "{whole}");
    for (text, want) in [
        (
            whole.lines().take(3).collect::<Vec<_>>().join("\n") + "\n",
            "the table lists 2 label(s), up to 2",
        ),
        ("garbage,,,\n".to_string(), "expected the header"),
        // (Label 2 is on the third line: the header is the first.)
        (whole.replacen("\n2,", "\n2,x", 1), "row 3: column 2"),
    ] {
        std::fs::write(&table, &text).unwrap();
        let (code, j, _) = check(&store);
        assert_eq!(code, Some(1), "{j}");
        let p = &j["problems"][0];
        assert_eq!(p["array"], "labels/cells label table", "{j}");
        assert!(p["error"].as_str().unwrap().contains(want), "{want}: {j}");
    }
    std::fs::write(&table, &whole).unwrap();
    assert_eq!(check(&store).0, Some(0));
}

#[test]
fn problems_info_lists_end_with_status_1() {
    // A label image the labels group does not name (a job stopped between
    // putting it in place and naming it), and a level whose array is gone:
    // `info` lists each as a problem and ends with status 1, with and
    // without --check.
    let d = tempfile::tempdir().unwrap();
    let store = clean_store(d.path());
    let o = run(&[
        "process",
        s(&store),
        "threshold(100)|label(6)",
        "--out",
        "cells",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = run(&["info", s(&store)]);
    assert_eq!(
        o.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&o.stdout)
    );
    let group = store.join("labels/zarr.json");
    let mut j: serde_json::Value = serde_json::from_slice(&std::fs::read(&group).unwrap()).unwrap();
    j["attributes"]["ome"]["labels"] = serde_json::json!([]);
    std::fs::write(&group, j.to_string()).unwrap();
    let unnamed = "labels/cells: not named in labels/zarr.json";
    let o = run(&["info", s(&store)]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert_eq!(o.status.code(), Some(1), "{out}");
    assert!(out.contains(unnamed), "{out}");
    let (code, j, _) = check(&store);
    assert_eq!(code, Some(1), "{j}");
    // A level's array gone: named as missing, not as a Zarr v2 file.
    let lv = d.path().join("lv.ome.zarr");
    copy_dir(&store, &lv);
    std::fs::remove_dir_all(lv.join("labels")).unwrap();
    std::fs::remove_file(lv.join("1/zarr.json")).unwrap();
    let o = run(&["info", s(&lv)]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert_eq!(o.status.code(), Some(1), "{out}");
    assert!(
        out.contains("problem: level 1:")
            && out.contains("no array here")
            && !out.contains(".zarray:"),
        "{out}"
    );
}

/// Levels no reader can open, and levels whose statistics are gone, are
/// problems of plain `info` too (exit 1): it read the metadata by hand
/// and passed them with status 0.
#[test]
fn levels_the_readers_refuse_are_problems_without_check() {
    let d = tempfile::tempdir().unwrap();
    let store = clean_store(d.path());
    let edit = |name: &str, f: &dyn Fn(&mut serde_json::Value)| -> PathBuf {
        let to = d.path().join(name);
        copy_dir(&store, &to);
        let p = to.join("0/zarr.json");
        let mut j: serde_json::Value = serde_json::from_slice(&std::fs::read(&p).unwrap()).unwrap();
        f(&mut j);
        std::fs::write(&p, j.to_string()).unwrap();
        to
    };
    let cases = [
        (
            edit("codec.ome.zarr", &|j| {
                j["codecs"][0]["configuration"]["codecs"][1] =
                    serde_json::json!({"name": "lzma", "configuration": {}})
            }),
            "level 0: cannot be read: codec lzma",
        ),
        (
            edit("fill.ome.zarr", &|j| j["fill_value"] = "banana".into()),
            "level 0: cannot be read",
        ),
        (
            edit("inner.ome.zarr", &|j| {
                j["codecs"][0]["configuration"]["chunk_shape"] = serde_json::json!([6, 6, 6])
            }),
            "level 0: inner chunks [6, 6, 6] do not divide its shards [16, 16, 16]",
        ),
        (
            edit("dtype.ome.zarr", &|j| j["data_type"] = "float32".into()),
            "level 1: its voxels are uint8, level 0's float32",
        ),
        (
            {
                let to = d.path().join("stats.ome.zarr");
                copy_dir(&store, &to);
                std::fs::remove_dir_all(to.join("_brickyard/stats/0")).unwrap();
                to
            },
            "level 0: its brick statistics (_brickyard/stats/0) are missing",
        ),
        (
            // Statistics there and unreadable: said (it read as "none
            // stored", also where a server did not answer).
            {
                let to = d.path().join("badstats.ome.zarr");
                copy_dir(&store, &to);
                let mut files = vec![to.join("_brickyard/stats/0")];
                let mut chunk = None;
                while let Some(p) = files.pop() {
                    for e in std::fs::read_dir(&p).unwrap() {
                        let e = e.unwrap().path();
                        if e.is_dir() {
                            files.push(e);
                        } else if e.file_name().unwrap() != "zarr.json" {
                            chunk = Some(e);
                        }
                    }
                }
                let f = std::fs::OpenOptions::new()
                    .write(true)
                    .open(chunk.unwrap())
                    .unwrap();
                f.set_len(10).unwrap();
                to
            },
            "level 0: its brick statistics (_brickyard/stats/0) cannot be read",
        ),
    ];
    assert_eq!(run(&["info", s(&store)]).status.code(), Some(0));
    for (st, want) in cases {
        let o = run(&["info", s(&st)]);
        let out = String::from_utf8_lossy(&o.stdout);
        assert_eq!(o.status.code(), Some(1), "{}: {out}", st.display());
        assert!(out.contains(&format!("problem: {want}")), "{want}: {out}");
    }
}

#[test]
fn a_failed_write_to_standard_output_is_an_error() {
    // `info > file` on a full disk left a truncated file and status 0.
    let d = tempfile::tempdir().unwrap();
    let store = clean_store(d.path());
    for json in [false, true] {
        let mut c = Command::new(env!("CARGO_BIN_EXE_brickyard"));
        c.args(["info", s(&store)]);
        if json {
            c.arg("--json");
        }
        let o = c
            .stdout(std::fs::File::create("/dev/full").unwrap())
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{err}");
        assert!(
            err.contains("standard output") && err.contains("incomplete"),
            "{err}"
        );
    }
}

/// `info` of a store whose conversion is still at work (its lock held by
/// a live process) says so; it said to remove the folder the conversion
/// was writing. A lock left by a process that is gone: interrupted.
#[test]
fn info_tells_a_conversion_at_work_from_an_interrupted_one() {
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("live.zarr");
    std::fs::create_dir(d.path().join("live.zarr.partial")).unwrap();
    let lock = d.path().join("live.zarr.lock");
    std::fs::write(&lock, format!("{}\n", std::process::id())).unwrap();
    let o = run(&["info", s(&store)]);
    let e = String::from_utf8_lossy(&o.stderr).to_string();
    assert_ne!(o.status.code(), Some(0), "{e}");
    assert!(
        e.contains("at work") && !e.contains("remove the folder"),
        "{e}"
    );
    std::fs::write(&lock, "4194305\n").unwrap();
    let e = String::from_utf8_lossy(&run(&["info", s(&store)]).stderr).to_string();
    assert!(
        e.contains("interrupted") && e.contains("remove the folder"),
        "{e}"
    );
}
