//! NRRD reading: the real file, then synthetic files of every layout and
//! encoding (attached/detached, raw/gzip, skips, channels, 2-D images,
//! data file lists), each compared box by box with the values written.

use super::*;

// -- the real file ------------------------------------------------------

#[test]
fn mr_brain_real_file() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/mr-brain-i16.nrrd");
    assert!(
        path.exists(),
        "the shared data folder is missing: {} not found (the real test volumes live in \
         ../shared/data next to the project root, see its README.md)",
        path.display()
    );
    let s = open(&path).unwrap();
    let m = s.meta();
    assert_eq!(m.dims, [25, 256, 256]);
    assert_eq!(m.channels, 1);
    assert_eq!(m.dtype, DType::I16);
    let sp = m.spacing.unwrap();
    for (a, b) in sp.iter().zip([6.5, 0.78125, 0.78125]) {
        assert!((a - b).abs() < 1e-9, "spacing {sp:?}");
    }
    // y steps by -0.78125 from 99.609375: read reversed, index 0 is the
    // file's last row, at 99.609375 - 255 · 0.78125.
    let o = m.origin.unwrap();
    for (a, b) in o.iter().zip([-78.0, -99.609375, -99.609375]) {
        assert!((a - b).abs() < 1e-9, "origin {o:?}");
    }
    assert_eq!(m.unit.as_deref(), Some("millimeter"));
    assert_eq!(
        m.notes.len(),
        1,
        "the reversed y axis is noted: {:?}",
        m.notes
    );
    assert!(
        m.notes[0].contains(
            "y runs against the file's direction -0.78125: stored reversed so that it runs \
             along +y (translation -99.609375"
        ),
        "{:?}",
        m.notes
    );

    // Independent decode: the payload follows the first blank line.
    let bytes = std::fs::read(&path).unwrap();
    let hdr_end = bytes.windows(2).position(|w| w == b"\n\n").unwrap() + 2;
    let mut expected = Vec::new();
    MultiGzDecoder::new(&bytes[hdr_end..])
        .read_to_end(&mut expected)
        .unwrap();
    assert_eq!(expected.len(), 256 * 256 * 25 * 2);
    let stored = expected.clone();
    // The volume as read: rows in reverse order within each slice.
    let row = 256 * 2;
    let expected: Vec<u8> = stored
        .chunks_exact(256 * row)
        .flat_map(|slice| slice.chunks_exact(row).rev().flatten().copied())
        .collect();
    let voxel = |z: usize, y: usize, x: usize| {
        let y = 255 - y;
        let i = ((z * 256 + y) * 256 + x) * 2;
        i16::from_le_bytes([stored[i], stored[i + 1]])
    };

    let whole = read_all(&s, 0);
    assert!(
        whole == expected,
        "whole volume differs from an independent decode"
    );
    let got = |z: u64, y: u64, x: u64| {
        let b = read_box(&s, 0, z..z + 1, y..y + 1, x..x + 1);
        i16::from_le_bytes([b[0], b[1]])
    };
    for (z, y, x) in [
        (12, 128, 128),
        (0, 0, 0),
        (24, 255, 255),
        (3, 100, 60),
        (20, 17, 200),
    ] {
        assert_eq!(got(z, y, x), voxel(z as usize, y as usize, x as usize));
    }
    let max = (0..expected.len() / 2)
        .map(|i| i16::from_le_bytes([expected[2 * i], expected[2 * i + 1]]))
        .max()
        .unwrap();
    assert!(max > 100, "the volume looks empty (max {max})");

    // Increasing z-slabs, as the pyramid builder reads.
    for z0 in (0..25).step_by(4) {
        let z = z0..(z0 + 4).min(25);
        let b = read_box(&s, 0, z.clone(), 0..256, 0..256);
        assert!(
            b == cut(&expected, m.dims, 2, &z, &(0..256), &(0..256)),
            "slab {z:?}"
        );
    }
    // Random boxes, out of z order.
    check_boxes(&s, 0, &expected, 12, 7);
    let back = read_box(&s, 0, 2..3, 10..20, 30..40);
    assert_eq!(
        back,
        cut(&expected, m.dims, 2, &(2..3), &(10..20), &(30..40))
    );
}

// -- synthetic files: layouts and encodings ------------------------------

#[test]
fn raw_little_endian_u16() {
    let dir = tempfile::tempdir().unwrap();
    let v = values(60);
    let hdr = format!("{HDR_U16}endian: little\nencoding: raw\nspacings: 0.5 0.25 2\n\n");
    let p = write(dir.path(), "le.nrrd", &[hdr.as_bytes(), &le(&v)]);
    let s = open(&p).unwrap();
    let m = s.meta();
    assert_eq!((m.dims, m.channels, m.dtype), ([3, 4, 5], 1, DType::U16));
    assert_eq!(m.spacing, Some([2.0, 0.25, 0.5]));
    assert_eq!((m.origin, m.unit.as_deref()), (None, None));
    assert_eq!(read_all(&s, 0), le(&v));
    check_boxes(&s, 0, &le(&v), 30, 1);
}

/// Fields that are deliberately not applied are named in the notes; the
/// stored numbers come back unchanged.
#[test]
fn unapplied_fields_are_noted() {
    let dir = tempfile::tempdir().unwrap();
    let v = values(60);
    let plain = format!(
        "{HDR_U16}endian: little\nencoding: raw\nspace: RAS\n\
         space directions: (0.5,0,0) (0,0.25,0) (0,0,2)\nspace origin: (1,2,3)\n\n"
    );
    let p = write(dir.path(), "plain.nrrd", &[plain.as_bytes(), &le(&v)]);
    assert!(open(&p).unwrap().meta().notes.is_empty());

    let hdr = format!(
        "{HDR_U16}endian: little\nencoding: raw\nspace: RAS\n\
         space directions: (0,0.25,0) (0.5,0,0) (0,0,2)\nold min: -1.5\nold max: 7\n\
         axis mins: 0 0 0\n\n"
    );
    let p = write(dir.path(), "noted.nrrd", &[hdr.as_bytes(), &le(&v)]);
    let s = open(&p).unwrap();
    let n = &s.meta().notes;
    assert_eq!(n.len(), 3, "{n:?}");
    assert!(
        n[0].starts_with("space directions (0,0.25,0) (0.5,0,0) (0,0,2) rotate or permute"),
        "{n:?}"
    );
    assert!(n[0].contains("not applied"));
    assert!(n[1].contains("(-1.5..7, the range before quantization) not applied"));
    assert!(n[2].starts_with("axis mins not applied"));
    assert_eq!(read_all(&s, 0), le(&v), "values are the stored numbers");
}

/// Axes whose space direction points backwards along their own world
/// axis are read reversed: the voxel at the reversed index is the file's,
/// and the translation and scale put every voxel where `space origin` +
/// i · direction does. Raw and gzip, with an interleaved channel axis.
#[test]
fn backward_directions_are_read_reversed() {
    let dir = tempfile::tempdir().unwrap();
    // x backwards, y forwards, z backwards; sizes x 5, y 4, z 3.
    let dirs = [[-0.5, 0.0, 0.0], [0.0, 0.25, 0.0], [0.0, 0.0, -2.0]];
    let org = [10.0, 20.0, 30.0];
    let (nx, ny, nz) = (5u64, 4u64, 3u64);
    let v = values(2 * 60);
    let flips = [true, false, true];
    let fmt = |a: [f64; 3]| format!("({},{},{})", a[0], a[1], a[2]);
    for (enc, data) in [("raw", le(&v)), ("gzip", gz(&le(&v)))] {
        let hdr = format!(
            "NRRD0004\ntype: unsigned short\ndimension: 4\nsizes: 2 5 4 3\n\
             kinds: vector domain domain domain\nendian: little\nencoding: {enc}\n\
             space: left-posterior-superior\nspace directions: none {} {} {}\n\
             space origin: {}\n\n",
            fmt(dirs[0]),
            fmt(dirs[1]),
            fmt(dirs[2]),
            fmt(org)
        );
        let p = write(dir.path(), &format!("{enc}.nrrd"), &[hdr.as_bytes(), &data]);
        let s = open(&p).unwrap();
        let m = s.meta();
        assert_eq!((m.dims, m.channels), ([3, 4, 5], 2));
        assert_eq!(m.spacing, Some([2.0, 0.25, 0.5]));
        assert_eq!(
            m.origin,
            Some([26.0, 20.0, 8.0]),
            "30 - 2 · 2, 20, 10 - 4 · 0.5"
        );
        assert_eq!(m.notes.len(), 1, "{:?}", m.notes);
        assert!(
            m.notes[0].contains(
                "x runs against the file's direction -0.5: stored reversed so that it runs \
                 along +x (translation 8, the position of the file's last x voxel); z runs \
                 against the file's direction -2"
            ),
            "{:?}",
            m.notes
        );
        let mir = |a: usize, i: u64, n: u64| if flips[a] { n - 1 - i } else { i };
        for c in 0..2 {
            // The file's channel c; the volume as read.
            let file: Vec<u16> = v.iter().skip(c).step_by(2).copied().collect();
            let mut want = Vec::new();
            for k in 0..nz {
                for j in 0..ny {
                    for i in 0..nx {
                        let (fi, fj, fk) = (mir(0, i, nx), mir(1, j, ny), mir(2, k, nz));
                        want.push(file[((fk * ny + fj) * nx + fi) as usize]);
                    }
                }
            }
            assert_eq!(read_all(&s, c), le(&want), "{enc} channel {c}");
            check_boxes(&s, c, &le(&want), 20, 3 + c as u64);
        }
        // World positions, from the header's vectors.
        let (sp, o) = (m.spacing.unwrap(), m.origin.unwrap());
        for f in [[0, 0, 0], [4, 3, 2], [1, 3, 0], [2, 0, 2]] {
            let file_world: Vec<f64> = (0..3)
                .map(|r| org[r] + (0..3).map(|a| f[a] as f64 * dirs[a][r]).sum::<f64>())
                .collect();
            let n = [nx, ny, nz];
            for a in 0..3 {
                let idx = mir(a, f[a], n[a]);
                let got = o[2 - a] + sp[2 - a] * idx as f64;
                assert!(
                    (got - file_world[a]).abs() < 1e-9,
                    "{enc}: file voxel {f:?} axis {a}: {got} in the store, {} in the file",
                    file_world[a]
                );
            }
        }
    }
}

#[test]
fn raw_big_endian_u16() {
    let dir = tempfile::tempdir().unwrap();
    let v = values(60);
    let hdr = format!("{HDR_U16}endian: big\nencoding: raw\n\n");
    let p = write(dir.path(), "be.nrrd", &[hdr.as_bytes(), &be(&v)]);
    let s = open(&p).unwrap();
    assert_eq!(read_all(&s, 0), le(&v));
    check_boxes(&s, 0, &le(&v), 30, 2);
}

#[test]
fn detached_raw_with_skips_and_geometry() {
    let dir = tempfile::tempdir().unwrap();
    let v = values(60);
    let hdr = "NRRD0005\n# a comment\ntype: uint16\ndimension: 3\nsizes: 5 4 3\n\
               endian: little\nencoding: raw\nline skip: 2\nbyte skip: 3\n\
               space: right-anterior-superior\n\
               space directions: (0,0.5,0) (-0.25,0,0) (0,0,2)\n\
               space origin: (1,2,3)\nspace units: \"um\" \"um\" \"um\"\n\
               some key:=some value\ndata file: vol.raw\n";
    let p = write(dir.path(), "vol.nhdr", &[hdr.as_bytes()]);
    write(
        dir.path(),
        "vol.raw",
        &[b"line one\nline two\nxyz", &le(&v)],
    );
    let s = open(&p).unwrap();
    let m = s.meta();
    assert_eq!(m.dims, [3, 4, 5]);
    assert_eq!(m.spacing, Some([2.0, 0.25, 0.5]));
    // x points along world y, y along world x (negated): origin follows.
    assert_eq!(m.origin, Some([3.0, 1.0, 2.0]));
    assert_eq!(m.unit.as_deref(), Some("micrometer"));
    assert_eq!(read_all(&s, 0), le(&v));
    check_boxes(&s, 0, &le(&v), 20, 3);
}

#[test]
fn detached_gzip_with_byte_skip_read_backwards() {
    let dir = tempfile::tempdir().unwrap();
    let v = values(20 * 9 * 7);
    let hdr = "NRRD0004\ntype: short\ndimension: 3\nsizes: 7 9 20\nendian: big\n\
               encoding: gz\nbyte skip: 4\ndatafile: vol.raw.gz\n\n";
    let p = write(dir.path(), "vol.nhdr", &[hdr.as_bytes()]);
    write(
        dir.path(),
        "vol.raw.gz",
        &[&gz(&[b"skip".as_slice(), &be(&v)].concat())],
    );
    let s = open(&p).unwrap();
    assert_eq!((s.meta().dims, s.meta().dtype), ([20, 9, 7], DType::I16));
    let full = le(&v);
    // Backwards in z: every request restarts the stream and must still work.
    for z in (0..20).rev() {
        assert_eq!(
            read_box(&s, 0, z..z + 1, 0..9, 0..7),
            cut(&full, [20, 9, 7], 2, &(z..z + 1), &(0..9), &(0..7))
        );
    }
    check_boxes(&s, 0, &full, 30, 4);
    assert_eq!(read_all(&s, 0), full);
}

#[test]
fn attached_gzip_from_several_threads() {
    let dir = tempfile::tempdir().unwrap();
    let v: Vec<u16> = values(16 * 32 * 33);
    let hdr =
        "NRRD0004\ntype: ushort\ndimension: 3\nsizes: 33 32 16\nendian: little\nencoding: gzip\n\n";
    let p = write(dir.path(), "t.nrrd", &[hdr.as_bytes(), &gz(&le(&v))]);
    let s = open(&p).unwrap();
    let full = le(&v);
    std::thread::scope(|sc| {
        for t in 0..4u64 {
            let (s, full) = (&s, &full);
            sc.spawn(move || {
                for z in (t..16).step_by(4) {
                    let b = read_box(s, 0, z..z + 1, 0..32, 0..33);
                    assert_eq!(
                        b,
                        cut(full, [16, 32, 33], 2, &(z..z + 1), &(0..32), &(0..33))
                    );
                }
                check_boxes(s, 0, full, 5, 10 + t);
            });
        }
    });
}

#[test]
fn gzip_streams_forward_only_as_far_as_needed() {
    let dir = tempfile::tempdir().unwrap();
    let v: Vec<u16> = values(10 * 8 * 9);
    let hdr =
        "NRRD0004\ntype: ushort\ndimension: 3\nsizes: 9 8 10\nendian: little\nencoding: gzip\n\n";
    let p = write(dir.path(), "f.nrrd", &[hdr.as_bytes(), &gz(&le(&v))]);
    let s = open(&p).unwrap();
    let opens = || s.gz_opens.load(std::sync::atomic::Ordering::Relaxed);
    let pos = || s.gz[0].lock().unwrap().cursor.as_ref().map(|c| c.pos);
    let slice = 8 * 9 * 2;
    assert_eq!((opens(), pos()), (0, None));
    for z in 0..10 {
        read_box(&s, 0, z..z + 1, 2..5, 0..9);
        assert_eq!(opens(), 1, "increasing z must not restart the stream");
        assert_eq!(
            pos(),
            Some(z * slice + 5 * 9 * 2),
            "decompressed past the request"
        );
    }
    read_box(&s, 0, 3..4, 0..8, 0..9);
    assert_eq!((opens(), pos()), (2, Some(4 * slice)));
}

/// `sizes: C 5 4 3`, channels fastest; the payload in NRRD order.
fn interleaved(channels: usize) -> (Vec<u16>, Vec<Vec<u8>>) {
    let v = values(channels * 60);
    let per_channel = (0..channels)
        .map(|c| {
            le(&v
                .iter()
                .skip(c)
                .step_by(channels)
                .copied()
                .collect::<Vec<_>>())
        })
        .collect();
    (v, per_channel)
}

#[test]
fn four_d_interleaved_channels_raw_and_gzip() {
    let dir = tempfile::tempdir().unwrap();
    let (v, chans) = interleaved(2);
    for (name, enc, data) in [
        ("i.nrrd", "raw", le(&v)),
        ("i.nrrd.gz.nrrd", "gzip", gz(&le(&v))),
    ] {
        let hdr = format!(
            "NRRD0004\ntype: uint16\ndimension: 4\nsizes: 2 5 4 3\nkinds: vector domain domain domain\n\
             endian: little\nencoding: {enc}\nspace directions: none (1,0,0) (0,1,0) (0,0,3)\n\n"
        );
        let p = write(dir.path(), name, &[hdr.as_bytes(), &data]);
        let s = open(&p).unwrap();
        assert_eq!((s.meta().dims, s.meta().channels), ([3, 4, 5], 2), "{enc}");
        assert_eq!(s.meta().spacing, Some([3.0, 1.0, 1.0]));
        for (c, full) in chans.iter().enumerate() {
            assert_eq!(&read_all(&s, c), full, "{enc} channel {c}");
        }
        // Alternate channels on the same boxes (served from the span cache
        // for gzip), then random boxes.
        let mut g = Lcg(5);
        for _ in 0..20 {
            let (z, y, x) = (g.range(3), g.range(4), g.range(5));
            for (c, full) in chans.iter().enumerate() {
                assert_eq!(
                    read_box(&s, c, z.clone(), y.clone(), x.clone()),
                    cut(full, [3, 4, 5], 2, &z, &y, &x)
                );
            }
        }
        check_boxes(&s, 1, &chans[1], 20, 6);
    }
}

#[test]
fn four_d_channels_from_space_directions_none() {
    let dir = tempfile::tempdir().unwrap();
    let (v, chans) = interleaved(3);
    let hdr = "NRRD0004\ntype: uint16\ndimension: 4\nsizes: 3 5 4 3\nendian: little\nencoding: raw\n\
               space: LPS\nspace directions: none (0.5,0,0) (0,0.5,0) (0,0,1)\nspace origin: (10,20,30)\n\n";
    let p = write(dir.path(), "n.nrrd", &[hdr.as_bytes(), &le(&v)]);
    let s = open(&p).unwrap();
    assert_eq!((s.meta().dims, s.meta().channels), ([3, 4, 5], 3));
    assert_eq!(s.meta().origin, Some([30.0, 20.0, 10.0]));
    assert_eq!(s.meta().unit.as_deref(), Some("millimeter"));
    for (c, full) in chans.iter().enumerate() {
        assert_eq!(&read_all(&s, c), full);
        check_boxes(&s, c, full, 10, c as u64);
    }
}

#[test]
fn four_d_planar_channels_gzip() {
    let dir = tempfile::tempdir().unwrap();
    let v = values(3 * 60);
    let hdr =
        "NRRD0004\ntype: uint16\ndimension: 4\nsizes: 5 4 3 3\nkinds: space space space list\n\
               endian: little\nencoding: gzip\n\n";
    let p = write(dir.path(), "p.nrrd", &[hdr.as_bytes(), &gz(&le(&v))]);
    let s = open(&p).unwrap();
    assert_eq!((s.meta().dims, s.meta().channels), ([3, 4, 5], 3));
    let chans: Vec<Vec<u8>> = (0..3).map(|c| le(&v[c * 60..(c + 1) * 60])).collect();
    // Channel by channel for each z slice, as a per-slab builder reads.
    for z in 0..3 {
        for (c, full) in chans.iter().enumerate() {
            assert_eq!(
                read_box(&s, c, z..z + 1, 0..4, 0..5),
                cut(full, [3, 4, 5], 2, &(z..z + 1), &(0..4), &(0..5))
            );
        }
    }
    for (c, full) in chans.iter().enumerate() {
        check_boxes(&s, c, full, 10, 20 + c as u64);
    }
}

#[test]
fn rgb_image_and_two_d_image() {
    let dir = tempfile::tempdir().unwrap();
    let (v, chans) = interleaved(3);
    let hdr = "NRRD0004\ntype: uint16\ndimension: 3\nsizes: 3 10 6\nkinds: RGB-color space space\n\
               endian: little\nencoding: raw\n\n";
    let p = write(dir.path(), "rgb.nrrd", &[hdr.as_bytes(), &le(&v)]);
    let s = open(&p).unwrap();
    assert_eq!((s.meta().dims, s.meta().channels), ([1, 6, 10], 3));
    assert_eq!(s.meta().channel_names, ["red", "green", "blue"]);
    for (c, full) in chans.iter().enumerate() {
        assert_eq!(&read_all(&s, c), full);
        check_boxes(&s, c, full, 10, 30 + c as u64);
    }

    let v = values(24);
    let hdr =
        "NRRD0001\ntype: uchar\ndimension: 2\nsizes: 6 4\nencoding: raw\nspacings: 0.1 0.2\n\n";
    let bytes: Vec<u8> = v.iter().map(|&x| x as u8).collect();
    let p = write(dir.path(), "2d.nrrd", &[hdr.as_bytes(), &bytes]);
    let s = open(&p).unwrap();
    assert_eq!((s.meta().dims, s.meta().dtype), ([1, 4, 6], DType::U8));
    assert_eq!(s.meta().spacing, Some([1.0, 0.2, 0.1]));
    assert_eq!(read_all(&s, 0), bytes);
    check_boxes(&s, 0, &bytes, 10, 40);
}

#[test]
fn byte_skip_minus_one_and_crlf_header() {
    let dir = tempfile::tempdir().unwrap();
    let v = values(60);
    let hdr =
        format!("{HDR_U16}endian: little\nencoding: raw\nbyte skip: -1\n\n").replace('\n', "\r\n");
    let p = write(
        dir.path(),
        "m1.nrrd",
        &[hdr.as_bytes(), b"junk bytes before the data", &le(&v)],
    );
    let s = open(&p).unwrap();
    assert_eq!(read_all(&s, 0), le(&v));
    check_boxes(&s, 0, &le(&v), 10, 50);
}

#[test]
fn data_file_list_and_printf_forms() {
    let dir = tempfile::tempdir().unwrap();
    let v = values(60);
    let full = le(&v);
    let slice = |z: usize| &full[z * 40..(z + 1) * 40];
    for z in 0..3 {
        write(dir.path(), &format!("slice{z}.raw"), &[slice(z)]);
        write(
            dir.path(),
            &format!("sl{:02}.raw.gz", 4 - 2 * z),
            &[&gz(slice(z))],
        );
    }
    let list = format!("{HDR_U16}endian: little\nencoding: raw\ndata file: LIST\nslice0.raw\nslice1.raw\nslice2.raw\n");
    let p = write(dir.path(), "list.nhdr", &[list.as_bytes()]);
    let s = open(&p).unwrap();
    assert_eq!(read_all(&s, 0), full);
    check_boxes(&s, 0, &full, 20, 60);

    // Descending numbers: sl04 is z = 0.
    let fmt =
        format!("{HDR_U16}endian: little\nencoding: gzip\ndata file: sl%02d.raw.gz 4 0 -2 2\n");
    let p = write(dir.path(), "fmt.nhdr", &[fmt.as_bytes()]);
    let s = open(&p).unwrap();
    assert_eq!(read_all(&s, 0), full);
    check_boxes(&s, 0, &full, 20, 61);
}

/// `line skip` streams past the lines without keeping them, and no
/// further than the data file's length: a file of one endless line (here
/// 8 MiB without a newline, and /dev/zero, which has no end) is refused
/// at once, naming the field, without holding the line in memory.
#[test]
fn line_skip_past_a_line_without_end_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("long.raw"), vec![7u8; 8 << 20]).unwrap();
    for (data, ends) in [
        ("long.raw", "ends after 0 of the 1 lines"),
        ("/dev/zero", "ends after 0 of the 1000000000 lines"),
    ] {
        let skip = if data == "long.raw" { 1 } else { 1_000_000_000 };
        let hdr = format!(
            "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 4 4 4\nencoding: raw\n\
             line skip: {skip}\ndata file: {data}\n"
        );
        let p = write(dir.path(), "skip.nhdr", &[hdr.as_bytes()]);
        let e = assert_error(&p, "skip.nhdr", "line skip");
        assert!(e.contains(ends), "{e}");
    }
}

/// Spacings: unknown (nan) on a spatial axis is not applied and said so;
/// an infinite one is an error naming the field.
#[test]
fn spacings_unknown_are_noted_and_infinite_refused() {
    let dir = tempfile::tempdir().unwrap();
    let v = values(60);
    let hdr = format!("{HDR_U16}endian: little\nencoding: raw\nspacings: nan 1 1\n\n");
    let p = write(dir.path(), "nan.nrrd", &[hdr.as_bytes(), &le(&v)]);
    let s = open(&p).unwrap();
    assert_eq!(s.meta().spacing, None);
    let n = &s.meta().notes;
    assert!(
        n.len() == 1
            && n[0].contains("spacings nan 1 1 unknown (nan) on a spatial axis: not applied"),
        "{n:?}"
    );
    let hdr = format!("{HDR_U16}endian: little\nencoding: raw\nspacings: 2 inf 3\n\n");
    let p = write(dir.path(), "inf.nrrd", &[hdr.as_bytes(), &le(&v)]);
    let e = assert_error(&p, "inf.nrrd", "spacings");
    assert!(e.contains("finite spacing"), "{e}");
}
