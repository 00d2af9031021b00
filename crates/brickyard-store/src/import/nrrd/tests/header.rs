//! NRRD header grammar and field semantics: every type spelling, the small
//! value parsers, bad inputs that must name their file and field, and
//! damaged files that must not panic.

use super::*;

#[test]
fn all_type_spellings() {
    let spellings: &[(&str, DType)] = &[
        ("uchar", DType::U8),
        ("unsigned char", DType::U8),
        ("uint8", DType::U8),
        ("uint8_t", DType::U8),
        ("signed char", DType::I8),
        ("int8", DType::I8),
        ("int8_t", DType::I8),
        ("short", DType::I16),
        ("short int", DType::I16),
        ("signed short", DType::I16),
        ("signed short int", DType::I16),
        ("int16", DType::I16),
        ("int16_t", DType::I16),
        ("ushort", DType::U16),
        ("unsigned short", DType::U16),
        ("unsigned short int", DType::U16),
        ("uint16", DType::U16),
        ("uint16_t", DType::U16),
        ("int", DType::I32),
        ("signed int", DType::I32),
        ("int32", DType::I32),
        ("int32_t", DType::I32),
        ("uint", DType::U32),
        ("unsigned int", DType::U32),
        ("uint32", DType::U32),
        ("uint32_t", DType::U32),
        ("float", DType::F32),
        ("double", DType::F64),
    ];
    for &(s, d) in spellings {
        assert!(matches!(nrrd_type(s), TypeName::Ok(t) if t == d), "{s}");
        assert!(
            matches!(nrrd_type(&s.to_uppercase().replace(' ', "  ")), TypeName::Ok(t) if t == d),
            "{s}"
        );
        assert_eq!(DType::parse(s), Some(d), "DType::parse disagrees on {s}");
    }
    for s in [
        "int64",
        "uint64_t",
        "long long",
        "unsigned long long int",
        "ulonglong",
        "longlong",
    ] {
        assert!(matches!(nrrd_type(s), TypeName::Wide), "{s}");
    }
    assert!(matches!(nrrd_type("block"), TypeName::Block));
    for s in ["u2", "<u2", "float32", "complex"] {
        assert!(matches!(nrrd_type(s), TypeName::Unknown), "{s}");
    }
}

#[test]
fn small_parsers() {
    let f = NameFormat::parse("slice%03d.raw").unwrap();
    assert_eq!(f.render(7), "slice007.raw");
    assert_eq!(f.render(-7), "slice-07.raw");
    assert_eq!(NameFormat::parse("%d").unwrap().render(12), "12");
    assert_eq!(NameFormat::parse("a%%%-4i|").unwrap().render(5), "a%5   |");
    assert_eq!(NameFormat::parse("%+.3u").unwrap().render(5), "+005");
    assert!(NameFormat::parse("%s").is_err());
    assert!(NameFormat::parse("%d%d").is_err());
    assert!(NameFormat::parse("plain").is_err());
    let h = Header {
        fields: vec![(
            "data file",
            "data file".into(),
            format!("x%d {} {} {}", i64::MIN, i64::MAX, 1i64 << 62),
        )],
        list: Vec::new(),
        end: None,
    };
    assert!(data_files(Path::new("h.nhdr"), &h, 3, &[1, 1, 4]).is_ok());
    assert_eq!(
        parse_vectors("(1, 2,3) none (4e-1,-5,6)").unwrap(),
        vec![Some(vec![1.0, 2.0, 3.0]), None, Some(vec![0.4, -5.0, 6.0])]
    );
    assert!(parse_vectors("(1,2").is_none());
    assert!(parse_vectors("(1,x,2)").is_none());
    assert_eq!(
        parse_quoted(r#""mm" "" "a\"b""#).unwrap(),
        ["mm", "", "a\"b"]
    );
    assert!(parse_quoted("mm mm").is_none());
    for (u, n) in [
        ("mm", "millimeter"),
        ("um", "micrometer"),
        ("µm", "micrometer"),
        ("nm", "nanometer"),
        ("m", "meter"),
    ] {
        assert_eq!(unit_name(u), Some(n));
    }
}

// -- bad inputs ---------------------------------------------------------

#[test]
fn bad_inputs_name_file_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let v = le(&values(60));
    let raw = format!("{HDR_U16}endian: little\nencoding: raw\n\n");

    let p = write(d, "truncated.nrrd", &[raw.as_bytes(), &v[..100]]);
    let e = assert_error(&p, "truncated.nrrd", "data");
    assert!(
        e.contains("holds 100 bytes after the header but sizes × type need 120"),
        "{e}"
    );

    let p = write(
        d,
        "sizes.nrrd",
        &[raw.replace("5 4 3", "5 4").as_bytes(), &v],
    );
    let e = assert_error(&p, "sizes.nrrd", "sizes");
    assert!(
        e.contains("sizes: expected 3 positive integers, found \"5 4\""),
        "{e}"
    );

    let p = write(
        d,
        "type.nrrd",
        &[raw.replace("unsigned short", "quadruple").as_bytes(), &v],
    );
    assert_error(&p, "type.nrrd", "type");
    let p = write(
        d,
        "int64.nrrd",
        &[raw.replace("unsigned short", "int64").as_bytes(), &v],
    );
    assert_error(&p, "int64.nrrd", "type");

    let p = write(
        d,
        "bzip2.nrrd",
        &[raw.replace("raw", "bzip2").as_bytes(), &v],
    );
    let e = assert_error(&p, "bzip2.nrrd", "encoding");
    assert!(e.contains("unsupported"), "{e}");
    let p = write(
        d,
        "ascii.nrrd",
        &[raw.replace("raw", "ascii").as_bytes(), &v],
    );
    assert_error(&p, "ascii.nrrd", "encoding");

    let gzh = raw.replace("raw", "gzip");
    let mut bad = gz(&v);
    let n = bad.len();
    for b in &mut bad[10..n - 8] {
        *b ^= 0x5a;
    }
    let p = write(d, "corrupt.nrrd", &[gzh.as_bytes(), &bad]);
    let e = assert_error(&p, "corrupt.nrrd", "data");
    assert!(
        e.contains("corrupt") || e.contains("truncated") || e.contains("ends after"),
        "{e}"
    );
    let p = write(d, "notgz.nrrd", &[gzh.as_bytes(), &v]);
    let e = assert_error(&p, "notgz.nrrd", "data");
    assert!(e.contains("gzip stream is corrupt"), "{e}");
    let p = write(d, "shortgz.nrrd", &[gzh.as_bytes(), &gz(&v[..50])]);
    let e = assert_error(&p, "shortgz.nrrd", "data");
    assert!(e.contains("ends after 50 bytes"), "{e}");
    let cut_gz = gz(&v);
    let p = write(
        d,
        "cutgz.nrrd",
        &[gzh.as_bytes(), &cut_gz[..cut_gz.len() / 2]],
    );
    assert_error(&p, "cutgz.nrrd", "data");
    // Bytes that decompress but do not match the trailer's CRC or length:
    // the CRC's first byte, the length's, and a voxel inside a stored
    // (uncompressed) deflate block.
    let good = gz(&v);
    let mut e = GzEncoder::new(Vec::new(), Compression::none());
    e.write_all(&v).unwrap();
    let mut flipped = e.finish().unwrap();
    let at = flipped.len() - 8 - 3;
    flipped[at] ^= 0x10;
    for (name, mut bytes, at) in [
        ("crc.nrrd", good.clone(), Some(good.len() - 8)),
        ("len.nrrd", good.clone(), Some(good.len() - 4)),
        ("flip.nrrd", flipped, None),
    ] {
        if let Some(at) = at {
            bytes[at] ^= 1;
        }
        let p = write(d, name, &[gzh.as_bytes(), &bytes]);
        let e = assert_error(&p, name, "data");
        assert!(
            e.contains("fails its check") && e.contains("checksum"),
            "{e}"
        );
    }

    let p = write(
        d,
        "missing.nhdr",
        &[format!("{HDR_U16}endian: little\nencoding: raw\ndata file: gone.raw\n").as_bytes()],
    );
    let e = assert_error(&p, "gone.raw", "data file");
    assert!(e.contains("missing.nhdr"), "{e}");

    let p = write(d, "magic.nrrd", &[b"NRRX0004\n", &v]);
    assert_error(&p, "magic.nrrd", "magic");
    let p = write(d, "empty.nrrd", &[]);
    assert_error(&p, "empty.nrrd", "magic");

    let p = write(
        d,
        "dim5.nrrd",
        &[raw.replace("dimension: 3", "dimension: 5").as_bytes()],
    );
    assert_error(&p, "dim5.nrrd", "dimension");
    let t = "NRRD0004\ntype: uchar\ndimension: 4\nsizes: 2 2 2 2\nkinds: space space space time\nencoding: raw\n\n";
    let p = write(d, "time.nrrd", &[t.as_bytes(), &[0u8; 16]]);
    assert_error(&p, "time.nrrd", "dimension");
    let p = write(
        d,
        "endian.nrrd",
        &[raw.replace("endian: little\n", "").as_bytes(), &v],
    );
    assert_error(&p, "endian.nrrd", "endian");
    let p = write(
        d,
        "skip.nrrd",
        &[
            gzh.to_string()
                .replace("\n\n", "\nbyte skip: -1\n\n")
                .as_bytes(),
            &gz(&v),
        ],
    );
    assert_error(&p, "skip.nrrd", "byte skip");
    let p = write(
        d,
        "twice.nrrd",
        &[
            raw.replace("encoding", "sizes: 5 4 3\nencoding").as_bytes(),
            &v,
        ],
    );
    assert_error(&p, "twice.nrrd", "sizes");
    let p = write(
        d,
        "noblank.nrrd",
        &[raw.trim_end().as_bytes(), b"\n\xff\xfe\x00\x01"],
    );
    assert_error(&p, "noblank.nrrd", "header");
    let p = write(
        d,
        "dirs.nrrd",
        &[
            raw.replace("\n\n", "\nspace directions: (1,0,0) (0,1,0)\n\n")
                .as_bytes(),
            &v,
        ],
    );
    assert_error(&p, "dirs.nrrd", "space directions");
    let p = write(
        d,
        "list.nhdr",
        &[format!("{HDR_U16}endian: little\nencoding: raw\ndata file: LIST\na.raw\n").as_bytes()],
    );
    assert_error(&p, "list.nhdr", "data file");
    let p = write(
        d,
        "lines.nrrd",
        &[
            raw.replace("\n\n", "\nline skip: 3\n\n").as_bytes(),
            b"one line\n",
        ],
    );
    assert_error(&p, "lines.nrrd", "line skip");
}

/// Truncated and mutated headers give errors, never panics.
#[test]
fn no_panic_on_damaged_files() {
    let dir = tempfile::tempdir().unwrap();
    let v = le(&values(60));
    for enc in ["raw", "gzip"] {
        let hdr = format!(
            "NRRD0004\ntype: ushort\ndimension: 3\nsizes: 5 4 3\nendian: little\nencoding: {enc}\n\
             space directions: (1,0,0) (0,1,0) (0,0,1)\nspace origin: (1,2,3)\nkinds: domain domain domain\n\n"
        );
        let data = if enc == "raw" { v.clone() } else { gz(&v) };
        let good = [hdr.as_bytes(), &data].concat();
        let p = dir.path().join("damaged.nrrd");
        let try_it = |bytes: &[u8]| {
            std::fs::write(&p, bytes).unwrap();
            if let Ok(s) = open(&p) {
                let m = s.meta().clone();
                if m.channel_bytes() < 1 << 20 {
                    for c in 0..m.channels {
                        let mut out = vec![0u8; m.channel_bytes() as usize];
                        let _ =
                            s.read_region(c, 0..m.dims[0], 0..m.dims[1], 0..m.dims[2], &mut out);
                    }
                }
            }
        };
        for n in 0..good.len() {
            try_it(&good[..n]);
        }
        for i in 0..hdr.len() {
            for b in [b'0', b'9', b' ', b'\n', b'-', b'(', 0xff] {
                let mut m = good.clone();
                m[i] = b;
                try_it(&m);
            }
        }
    }
}
