//! `s3://bucket/key…` locations: each request becomes an HTTPS request to
//! the bucket's endpoint, signed with AWS Signature Version 4 as a
//! presigned URL (only the `host` header is signed, so a `Range` header
//! may be added), or unsigned for public buckets. The requests themselves,
//! their retries, bounds and errors, are those of [`super::http`].
//!
//! Settings come from the usual environment variables:
//! - `AWS_ENDPOINT_URL_S3` or `AWS_ENDPOINT_URL`: an S3-compatible server
//!   (MinIO, Ceph, a cloud's own), addressed path style
//!   (`endpoint/bucket/key`); without one, Amazon's regional endpoint,
//!   addressed virtual-host style (`bucket.s3.region.amazonaws.com`) where
//!   the bucket's name allows it.
//! - `AWS_REGION` or `AWS_DEFAULT_REGION` (default `us-east-1`).
//! - `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_SESSION_TOKEN`;
//!   else the profile `AWS_PROFILE` (default `default`) of
//!   `~/.aws/credentials` (`AWS_SHARED_CREDENTIALS_FILE`), with its region
//!   from `~/.aws/config` (`AWS_CONFIG_FILE`) when no variable gives one.
//!   Without a key pair, or with `AWS_NO_SIGN_REQUEST=true`, requests go
//!   unsigned (anonymous reads of public buckets).

use rusty_s3::actions::{GetObject, HeadObject, S3Action};
use rusty_s3::{Bucket, Credentials, UrlStyle};
use std::sync::RwLock;
use std::time::Duration;

/// How long a signed request stays valid (it is made just before it is
/// sent, once per attempt).
const EXPIRES: Duration = Duration::from_secs(15 * 60);

/// Where and how `s3://` locations are read.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct S3Config {
    /// An S3-compatible endpoint (`http(s)://host[:port]`), addressed path
    /// style; `None`: Amazon's regional endpoint.
    pub endpoint: Option<String>,
    pub region: String,
    /// Access key id, secret and session token; `None`: unsigned requests.
    pub credentials: Option<(String, String, Option<String>)>,
}

impl Default for S3Config {
    fn default() -> Self {
        S3Config {
            endpoint: None,
            region: "us-east-1".into(),
            credentials: None,
        }
    }
}

impl S3Config {
    /// The settings from the environment (see the module's text); a value
    /// that cannot be used is an error naming the variable.
    pub fn from_env() -> Result<Self, String> {
        Self::from_vars(|k| std::env::var(k).ok())
    }

    /// [`S3Config::from_env`] over any source of variables.
    pub fn from_vars(get: impl Fn(&str) -> Option<String>) -> Result<Self, String> {
        let var = |k: &str| {
            get(k)
                .map(|v| v.trim().to_string())
                .filter(|v| !v.is_empty())
        };
        let mut c = S3Config::default();
        for k in ["AWS_ENDPOINT_URL_S3", "AWS_ENDPOINT_URL"] {
            if let Some(e) = var(k) {
                let l = e.to_ascii_lowercase();
                if !(l.starts_with("http://") || l.starts_with("https://")) {
                    return Err(format!(
                        "{k}: expected an http:// or https:// address, found {e:?}"
                    ));
                }
                c.endpoint = Some(e.trim_end_matches('/').to_string());
                break;
            }
        }
        // The shared files: `~/.aws/credentials` and `~/.aws/config` (or
        // where AWS_SHARED_CREDENTIALS_FILE and AWS_CONFIG_FILE say), the
        // profile AWS_PROFILE names or `default`.
        let named = var("AWS_PROFILE");
        let profile = named.clone().unwrap_or_else(|| "default".into());
        let home = var("HOME").map(std::path::PathBuf::from);
        let file = |v: &str, name: &str| {
            var(v)
                .map(std::path::PathBuf::from)
                .or_else(|| home.as_ref().map(|h| h.join(".aws").join(name)))
        };
        let creds_file = file("AWS_SHARED_CREDENTIALS_FILE", "credentials");
        let config_file = file("AWS_CONFIG_FILE", "config");
        let creds_section = read_profile(creds_file.as_deref(), &profile)?;
        let config_section = read_profile(
            config_file.as_deref(),
            &if profile == "default" {
                profile.clone()
            } else {
                format!("profile {profile}")
            },
        )?;
        if let (Some(p), None, None) = (&named, &creds_section, &config_section) {
            return Err(format!(
                "AWS_PROFILE: no profile {p:?} in {} or {}",
                show(creds_file.as_deref()),
                show(config_file.as_deref())
            ));
        }
        let from_config = config_section
            .as_ref()
            .and_then(|(_, m)| m.get("region").cloned())
            .map(|r| (r, format!("region in {}", show(config_file.as_deref()))));
        let region = var("AWS_REGION")
            .map(|r| (r, "AWS_REGION".to_string()))
            .or_else(|| var("AWS_DEFAULT_REGION").map(|r| (r, "AWS_REGION".to_string())))
            .or(from_config);
        if let Some((r, from)) = region {
            if !r
                .chars()
                .all(|ch| ch.is_ascii_alphanumeric() || ch == '-' || ch == '_')
            {
                return Err(format!(
                    "{from}: expected a region name such as eu-west-1, found {r:?}"
                ));
            }
            c.region = r;
        }
        let anonymous = match var("AWS_NO_SIGN_REQUEST").map(|v| v.to_ascii_lowercase()) {
            None => false,
            Some(v) if v == "true" || v == "1" || v == "yes" => true,
            Some(v) if v == "false" || v == "0" || v == "no" => false,
            Some(v) => {
                return Err(format!(
                    "AWS_NO_SIGN_REQUEST: expected true or false, found {v:?}"
                ))
            }
        };
        match (var("AWS_ACCESS_KEY_ID"), var("AWS_SECRET_ACCESS_KEY")) {
            _ if anonymous => {}
            (Some(k), Some(s)) => c.credentials = Some((k, s, var("AWS_SESSION_TOKEN"))),
            (None, None) => {
                if let Some((path, m)) = &creds_section {
                    let get = |k: &str| m.get(k).filter(|v| !v.is_empty()).cloned();
                    match (get("aws_access_key_id"), get("aws_secret_access_key")) {
                        (Some(k), Some(s)) => {
                            c.credentials = Some((k, s, get("aws_session_token")))
                        }
                        (None, None) => {}
                        _ => {
                            return Err(format!(
                                "{}: profile {profile:?}: aws_access_key_id and \
                                 aws_secret_access_key go together (both or neither)",
                                path.display()
                            ))
                        }
                    }
                }
            }
            (Some(_), None) => {
                return Err(
                    "AWS_SECRET_ACCESS_KEY: not set, but AWS_ACCESS_KEY_ID is (both or neither; \
                     AWS_NO_SIGN_REQUEST=true for anonymous reads)"
                        .into(),
                )
            }
            (None, Some(_)) => {
                return Err(
                    "AWS_ACCESS_KEY_ID: not set, but AWS_SECRET_ACCESS_KEY is (both or neither)"
                        .into(),
                )
            }
        }
        Ok(c)
    }
}

type Section = std::collections::HashMap<String, String>;

/// The keys of section `name` of the INI file at `path`; `None` when
/// there is no such file or section. A file that cannot be read or parsed
/// is an error naming it.
fn read_profile(
    path: Option<&std::path::Path>,
    name: &str,
) -> Result<Option<(std::path::PathBuf, Section)>, String> {
    let Some(path) = path.filter(|p| p.exists()) else {
        return Ok(None);
    };
    let ini = ini::Ini::load_from_file(path).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(ini.section(Some(name)).map(|props| {
        let m = props
            .iter()
            .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
            .collect();
        (path.to_path_buf(), m)
    }))
}

fn show(p: Option<&std::path::Path>) -> String {
    p.map_or("(no file)".into(), |p| p.display().to_string())
}

static CONFIG: RwLock<Option<S3Config>> = RwLock::new(None);

/// Set how `s3://` locations are read (the CLI does, once at start, after
/// checking the environment); otherwise [`S3Config::from_env`] is used,
/// or the defaults where it fails.
pub fn configure(cfg: S3Config) {
    *CONFIG.write().unwrap_or_else(|e| e.into_inner()) = Some(cfg);
}

fn config() -> S3Config {
    if let Some(c) = CONFIG.read().unwrap_or_else(|e| e.into_inner()).as_ref() {
        return c.clone();
    }
    let c = S3Config::from_env().unwrap_or_default();
    CONFIG
        .write()
        .unwrap_or_else(|e| e.into_inner())
        .get_or_insert(c)
        .clone()
}

/// Whether `s` is an `s3://` location.
pub fn is_s3(s: &str) -> bool {
    s.get(..5).is_some_and(|p| p.eq_ignore_ascii_case("s3://"))
}

/// `s3://bucket/key` → `(bucket, key)`; the key may be empty (the bucket's
/// root). Repeated slashes (a `Path::join` artefact) are collapsed.
pub fn split(s: &str) -> Result<(&str, String), String> {
    let rest = s
        .get(5..)
        .filter(|_| is_s3(s))
        .ok_or_else(|| format!("{s}: not an s3:// location"))?;
    let (bucket, key) = rest.split_once('/').unwrap_or((rest, ""));
    let valid = (3..=63).contains(&bucket.len())
        && bucket
            .chars()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-' || c == '.');
    if !valid {
        return Err(format!(
            "{s}: the bucket name {bucket:?} is not valid (3 to 63 characters: \
             lower-case letters, digits, '-' and '.')"
        ));
    }
    let key: Vec<&str> = key.split('/').filter(|k| !k.is_empty()).collect();
    Ok((bucket, key.join("/")))
}

/// The HTTP(S) request for `method` (`GET` or `HEAD`) of the `s3://`
/// location `s`, signed now when there are credentials.
pub fn request_url(s: &str, method: &str) -> Result<String, String> {
    request_url_with(&config(), s, method, jiff::Timestamp::now())
}

/// [`request_url`] with given settings and signing time.
pub fn request_url_with(
    cfg: &S3Config,
    s: &str,
    method: &str,
    time: jiff::Timestamp,
) -> Result<String, String> {
    let (name, key) = split(s)?;
    let (endpoint, style) = match &cfg.endpoint {
        Some(e) => (e.clone(), UrlStyle::Path),
        None => (
            format!("https://s3.{}.amazonaws.com", cfg.region),
            // Names with dots break the certificate of virtual hosts.
            if name.contains('.') {
                UrlStyle::Path
            } else {
                UrlStyle::VirtualHost
            },
        ),
    };
    let url = endpoint
        .parse()
        .map_err(|e| format!("S3 endpoint {endpoint:?}: {e}"))?;
    let bucket = Bucket::new(url, style, name.to_string(), cfg.region.clone())
        .map_err(|e| format!("S3 endpoint {endpoint:?}: {e}"))?;
    // The object's address must parse before the action is signed.
    bucket
        .object_url(&key)
        .map_err(|e| format!("{s}: the key does not make an address: {e}"))?;
    let creds = cfg.credentials.as_ref().map(|(k, s, t)| match t {
        Some(t) => Credentials::new_with_token(k.clone(), s.clone(), t.clone()),
        None => Credentials::new(k.clone(), s.clone()),
    });
    let url = match method {
        "GET" => GetObject::new(&bucket, creds.as_ref(), &key).sign_with_time(EXPIRES, &time),
        "HEAD" => HeadObject::new(&bucket, creds.as_ref(), &key).sign_with_time(EXPIRES, &time),
        m => return Err(format!("{s}: no {m} requests on S3 stores")),
    };
    // An unsigned address comes with an empty query.
    Ok(url.as_str().trim_end_matches('?').to_string())
}

/// Whether requests are signed (for the text of a 403).
pub fn signed() -> bool {
    config().credentials.is_some()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn vars<'a>(v: &'a [(&'a str, &'a str)]) -> impl Fn(&str) -> Option<String> + 'a {
        move |k| v.iter().find(|(n, _)| *n == k).map(|(_, x)| x.to_string())
    }

    /// The presigned GET of Amazon's Signature Version 4 documentation
    /// ("Authenticating Requests: Using Query Parameters", example for
    /// `examplebucket/test.txt`, 24 May 2013, 86 400 s): its signature,
    /// recomputed here with the documentation's key pair, must come out.
    #[test]
    fn presigned_get_matches_the_documented_example() {
        let cfg = S3Config {
            endpoint: None,
            region: "us-east-1".into(),
            credentials: Some((
                "AKIAIOSFODNN7EXAMPLE".into(),
                "wJalrXUtnFEMI/K7MDENG/bPxRfiCYEXAMPLEKEY".into(),
                None,
            )),
        };
        let name = "examplebucket";
        let bucket = Bucket::new(
            "https://s3.amazonaws.com".parse().unwrap(),
            UrlStyle::VirtualHost,
            name,
            "us-east-1",
        )
        .unwrap();
        let creds = Credentials::new(
            "AKIAIOSFODNN7EXAMPLE",
            cfg.credentials.as_ref().unwrap().1.clone(),
        );
        let t: jiff::Timestamp = "2013-05-24T00:00:00Z".parse().unwrap();
        let url = GetObject::new(&bucket, Some(&creds), "test.txt")
            .sign_with_time(Duration::from_secs(86400), &t)
            .to_string();
        assert!(
            url.ends_with(
                "X-Amz-Signature=aeeed9bbccd4d02ee5c0109b86d86835f995330da4c265957d157751f604d404"
            ),
            "{url}"
        );
        // Through this module: the regional endpoint, virtual host, the
        // same credential scope; 15 minutes of validity.
        let ours = request_url_with(&cfg, "s3://examplebucket/test.txt", "GET", t).unwrap();
        assert!(
            ours.starts_with("https://examplebucket.s3.us-east-1.amazonaws.com/test.txt?"),
            "{ours}"
        );
        assert!(
            ours.contains(
                "X-Amz-Credential=AKIAIOSFODNN7EXAMPLE%2F20130524%2Fus-east-1%2Fs3%2Faws4_request"
            ),
            "{ours}"
        );
        assert!(ours.contains("X-Amz-Expires=900"), "{ours}");
        assert!(ours.contains("X-Amz-SignedHeaders=host"), "{ours}");
        // HEAD is signed for its own method.
        let head = request_url_with(&cfg, "s3://examplebucket/test.txt", "HEAD", t).unwrap();
        assert_ne!(head, ours);
    }

    #[test]
    fn locations_and_endpoints() {
        assert_eq!(
            split("s3://my-bucket/a/b.ome.zarr//zarr.json").unwrap(),
            ("my-bucket", "a/b.ome.zarr/zarr.json".to_string())
        );
        assert_eq!(split("S3://abc").unwrap(), ("abc", String::new()));
        assert!(split("s3://Bad_Bucket/x")
            .unwrap_err()
            .contains("not valid"));
        assert!(split("s3://ab/x").is_err());
        let cfg = S3Config {
            endpoint: Some("http://127.0.0.1:9000".into()),
            ..Default::default()
        };
        let t = jiff::Timestamp::UNIX_EPOCH;
        // Anonymous, custom endpoint: a plain path-style address.
        assert_eq!(
            request_url_with(&cfg, "s3://data.lab/v/zarr.json", "GET", t).unwrap(),
            "http://127.0.0.1:9000/data.lab/v/zarr.json"
        );
        // Amazon, a name with dots: path style.
        let aws = S3Config::default();
        assert_eq!(
            request_url_with(&aws, "s3://data.lab/v", "HEAD", t).unwrap(),
            "https://s3.us-east-1.amazonaws.com/data.lab/v"
        );
        assert!(request_url_with(&aws, "s3://abc/v", "PUT", t).is_err());
    }

    #[test]
    fn profiles_from_the_shared_files() {
        let d = tempfile::tempdir().unwrap();
        let aws = d.path().join(".aws");
        std::fs::create_dir(&aws).unwrap();
        std::fs::write(
            aws.join("credentials"),
            "[default]\naws_access_key_id = AKDEF\naws_secret_access_key = sdef\n\n\
             [lab]\naws_access_key_id=AKLAB\naws_secret_access_key=slab\naws_session_token=tlab\n\
             [half]\naws_access_key_id=AKHALF\n",
        )
        .unwrap();
        std::fs::write(
            aws.join("config"),
            "[default]\nregion = eu-west-1\n[profile lab]\nregion=us-west-2\n[profile bad]\nregion=a b\n",
        )
        .unwrap();
        let home = d.path().to_str().unwrap();
        let c = S3Config::from_vars(vars(&[("HOME", home)])).unwrap();
        assert_eq!(c.credentials, Some(("AKDEF".into(), "sdef".into(), None)));
        assert_eq!(c.region, "eu-west-1");
        let c = S3Config::from_vars(vars(&[("HOME", home), ("AWS_PROFILE", "lab")])).unwrap();
        assert_eq!(
            c.credentials,
            Some(("AKLAB".into(), "slab".into(), Some("tlab".into())))
        );
        assert_eq!(c.region, "us-west-2");
        // The variables win over the files.
        let c = S3Config::from_vars(vars(&[
            ("HOME", home),
            ("AWS_ACCESS_KEY_ID", "k"),
            ("AWS_SECRET_ACCESS_KEY", "s"),
            ("AWS_REGION", "ap-south-1"),
        ]))
        .unwrap();
        assert_eq!(c.credentials, Some(("k".into(), "s".into(), None)));
        assert_eq!(c.region, "ap-south-1");
        // Anonymous whatever the files hold.
        let c = S3Config::from_vars(vars(&[("HOME", home), ("AWS_NO_SIGN_REQUEST", "1")])).unwrap();
        assert_eq!(c.credentials, None);
        // Errors name the file, the profile or the variable.
        let e = S3Config::from_vars(vars(&[("HOME", home), ("AWS_PROFILE", "nope")])).unwrap_err();
        assert!(
            e.starts_with("AWS_PROFILE") && e.contains("\"nope\""),
            "{e}"
        );
        let e = S3Config::from_vars(vars(&[("HOME", home), ("AWS_PROFILE", "half")])).unwrap_err();
        assert!(e.contains("credentials") && e.contains("\"half\""), "{e}");
        let e = S3Config::from_vars(vars(&[("HOME", home), ("AWS_PROFILE", "bad")])).unwrap_err();
        assert!(e.contains("config") && e.contains("region"), "{e}");
        // No files: no credentials, the default region.
        let c = S3Config::from_vars(vars(&[("HOME", "/nonexistent")])).unwrap();
        assert_eq!((c.credentials, c.region.as_str()), (None, "us-east-1"));
    }

    #[test]
    fn settings_from_the_environment() {
        let c = S3Config::from_vars(vars(&[
            ("AWS_ENDPOINT_URL", "http://localhost:9000/"),
            ("AWS_DEFAULT_REGION", "eu-west-1"),
            ("AWS_ACCESS_KEY_ID", "k"),
            ("AWS_SECRET_ACCESS_KEY", "s"),
            ("AWS_SESSION_TOKEN", "t"),
        ]))
        .unwrap();
        assert_eq!(c.endpoint.as_deref(), Some("http://localhost:9000"));
        assert_eq!(c.region, "eu-west-1");
        assert_eq!(
            c.credentials,
            Some(("k".into(), "s".into(), Some("t".into())))
        );
        // The S3-specific endpoint wins; anonymous on request.
        let c = S3Config::from_vars(vars(&[
            ("AWS_ENDPOINT_URL", "http://a:1"),
            ("AWS_ENDPOINT_URL_S3", "http://b:2"),
            ("AWS_ACCESS_KEY_ID", "k"),
            ("AWS_SECRET_ACCESS_KEY", "s"),
            ("AWS_NO_SIGN_REQUEST", "true"),
        ]))
        .unwrap();
        assert_eq!(c.endpoint.as_deref(), Some("http://b:2"));
        assert_eq!(c.credentials, None);
        for (bad, names) in [
            (
                vec![("AWS_ENDPOINT_URL", "localhost:9000")],
                "AWS_ENDPOINT_URL",
            ),
            (vec![("AWS_REGION", "eu west")], "AWS_REGION"),
            (vec![("AWS_ACCESS_KEY_ID", "k")], "AWS_SECRET_ACCESS_KEY"),
            (
                vec![("AWS_NO_SIGN_REQUEST", "maybe")],
                "AWS_NO_SIGN_REQUEST",
            ),
        ] {
            let e = S3Config::from_vars(vars(&bad)).unwrap_err();
            assert!(e.starts_with(names), "{e}");
        }
    }
}
