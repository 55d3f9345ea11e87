//! The server's TLS identity: a self-signed certificate generated at first start (rcgen), saved in the data
//! directory and reused, and its SHA-256 fingerprint, which clients pin. Beside it, the short-lived certificate
//! that browsers pin for WebTransport ([`WebCertificate`]), picked per handshake by ALPN.

use std::path::{Path, PathBuf};
use std::sync::{Arc, RwLock};
use std::time::{Duration, SystemTime};

use canopy_protocol::messages::certificate_fingerprint;
use quinn::rustls;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer};

/// Names the certificate is issued for.
pub(crate) const CERT_NAMES: [&str; 2] = ["localhost", "canopy"];

/// A certificate and its private key.
#[derive(Debug)]
pub struct Identity {
    /// The certificate, DER.
    pub cert: CertificateDer<'static>,
    /// The private key, PKCS#8 DER.
    pub key: PrivatePkcs8KeyDer<'static>,
    /// Whether it was generated now (rather than loaded).
    pub generated: bool,
    /// Where it is saved (`None`: in memory only).
    pub path: Option<PathBuf>,
}

/// Why the identity could not be loaded, generated or saved.
#[derive(Debug, thiserror::Error)]
pub enum IdentityError {
    /// Reading or writing the data directory failed.
    #[error("{path}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// What failed.
        source: std::io::Error,
    },
    /// rcgen could not generate a certificate.
    #[error("generating the certificate: {0}")]
    Generate(#[from] rcgen::Error),
    /// rustls rejected the certificate or key.
    #[error("the certificate or key is not usable: {0}")]
    Tls(#[from] rustls::Error),
}

impl Identity {
    /// A fresh self-signed identity, held in memory only.
    pub fn generate() -> Result<Identity, IdentityError> {
        let names: Vec<String> = CERT_NAMES.iter().map(|s| s.to_string()).collect();
        let ck = rcgen::generate_simple_self_signed(names)?;
        Ok(Identity {
            cert: ck.cert.der().clone(),
            key: PrivatePkcs8KeyDer::from(ck.signing_key.serialize_der()),
            generated: true,
            path: None,
        })
    }

    /// Load `cert.der` and `key.der` from `dir`, or generate them there at first start.
    pub fn load_or_generate(dir: &Path) -> Result<Identity, IdentityError> {
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| IdentityError::Io { path, source }
        };
        if dir.exists() && !dir.is_dir() {
            let source = std::io::Error::other("not a directory (the data directory keeps the certificate and edits)");
            return Err(IdentityError::Io { path: dir.to_path_buf(), source });
        }
        let (cert_path, key_path) = (dir.join("cert.der"), dir.join("key.der"));
        if cert_path.exists() && key_path.exists() {
            // A certificate or key is a few KiB; anything but a small regular file is refused.
            let read = |p: &Path| canopy_worlds::fsread::read_bounded(p, 1 << 20).map_err(std::io::Error::other);
            let cert = read(&cert_path).map_err(io(&cert_path))?;
            let key = read(&key_path).map_err(io(&key_path))?;
            return Ok(Identity {
                cert: CertificateDer::from(cert),
                key: PrivatePkcs8KeyDer::from(key),
                generated: false,
                path: Some(dir.to_path_buf()),
            });
        }
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let mut id = Identity::generate()?;
        std::fs::write(&cert_path, id.cert.as_ref()).map_err(io(&cert_path))?;
        write_private(&key_path, id.key.secret_pkcs8_der()).map_err(io(&key_path))?;
        id.path = Some(dir.to_path_buf());
        Ok(id)
    }

    /// The SHA-256 fingerprint of the certificate, lowercase hex: what clients pin.
    pub fn fingerprint(&self) -> String {
        certificate_fingerprint(self.cert.as_ref())
    }

    /// A rustls server configuration for both kinds of client on one port: ALPN `canopy/1` gets this identity,
    /// ALPN `h3` (WebTransport, a browser) the current certificate of `web`. TLS 1.3 only.
    pub fn server_config(&self, web: &Arc<WebCertificate>) -> Result<Arc<rustls::ServerConfig>, IdentityError> {
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let native = certified(&provider, self.cert.clone(), self.key.clone_key())?;
        let resolver = ByAlpn { native, web: Arc::clone(web) };
        let mut cfg = rustls::ServerConfig::builder_with_provider(provider)
            .with_protocol_versions(&[&rustls::version::TLS13])?
            .with_no_client_auth()
            .with_cert_resolver(Arc::new(resolver));
        cfg.alpn_protocols = vec![canopy_protocol::ALPN.to_vec(), WEB_ALPN.to_vec()];
        Ok(Arc::new(cfg))
    }
}

/// The ALPN of HTTP/3, under which browsers speak WebTransport.
pub(crate) const WEB_ALPN: &[u8] = b"h3";

/// How long a WebTransport certificate is valid. Browsers accept a pinned certificate (`serverCertificateHashes`)
/// only when it is valid for at most 14 days.
pub const WEB_CERT_VALIDITY: Duration = Duration::from_secs(10 * 24 * 3600);

/// How old a WebTransport certificate gets before a new one replaces it: a hash handed to a page stays good for
/// at least the rest of its validity (5 days) after it stops being served.
pub const WEB_CERT_ROTATION: Duration = Duration::from_secs(5 * 24 * 3600);

/// The short-lived, in-memory certificate browsers pin for WebTransport: ECDSA P-256, valid
/// [`WEB_CERT_VALIDITY`] from an hour before it was made (clock skew), replaced by [`WebCertificate::rotate`]
/// once it is [`WEB_CERT_ROTATION`] old. New handshakes get the current one.
#[derive(Debug)]
pub struct WebCertificate {
    current: RwLock<WebCert>,
}

#[derive(Clone, Debug)]
struct WebCert {
    key: Arc<rustls::sign::CertifiedKey>,
    fingerprint: String,
    made: SystemTime,
}

impl WebCertificate {
    /// A fresh certificate, made at `now`.
    pub fn generate(now: SystemTime) -> Result<WebCertificate, IdentityError> {
        Ok(WebCertificate { current: RwLock::new(WebCert::generate(now)?) })
    }

    /// The current certificate's SHA-256 fingerprint, lowercase hex: what a page passes to
    /// `serverCertificateHashes`.
    pub fn fingerprint(&self) -> String {
        self.read().fingerprint
    }

    /// The current certificate's DER.
    pub fn der(&self) -> CertificateDer<'static> {
        self.read().key.cert[0].clone()
    }

    /// Replace the certificate when it is at least [`WEB_CERT_ROTATION`] old at `now`; whether it did.
    pub fn rotate(&self, now: SystemTime) -> Result<bool, IdentityError> {
        let made = self.read().made;
        if now.duration_since(made).unwrap_or_default() < WEB_CERT_ROTATION {
            return Ok(false);
        }
        let fresh = WebCert::generate(now)?;
        *self.current.write().unwrap_or_else(|p| p.into_inner()) = fresh;
        Ok(true)
    }

    fn read(&self) -> WebCert {
        self.current.read().unwrap_or_else(|p| p.into_inner()).clone()
    }
}

impl WebCert {
    fn generate(now: SystemTime) -> Result<WebCert, IdentityError> {
        let names: Vec<String> = CERT_NAMES.iter().map(|s| s.to_string()).collect();
        let mut params = rcgen::CertificateParams::new(names)?;
        let unix = |t: SystemTime| {
            let secs = t.duration_since(SystemTime::UNIX_EPOCH).unwrap_or_default().as_secs() as i64;
            time::OffsetDateTime::from_unix_timestamp(secs).unwrap_or(time::OffsetDateTime::UNIX_EPOCH)
        };
        let from = now.checked_sub(Duration::from_secs(3600)).unwrap_or(now);
        params.not_before = unix(from);
        params.not_after = unix(from + WEB_CERT_VALIDITY);
        let key = rcgen::KeyPair::generate_for(&rcgen::PKCS_ECDSA_P256_SHA256)?;
        let cert = params.self_signed(&key)?;
        let provider = rustls::crypto::ring::default_provider();
        let der = cert.der().clone();
        let fingerprint = certificate_fingerprint(der.as_ref());
        let key = certified(&provider, der, PrivatePkcs8KeyDer::from(key.serialize_der()))?;
        Ok(WebCert { key, fingerprint, made: now })
    }
}

fn certified(
    provider: &rustls::crypto::CryptoProvider,
    cert: CertificateDer<'static>,
    key: PrivatePkcs8KeyDer<'static>,
) -> Result<Arc<rustls::sign::CertifiedKey>, IdentityError> {
    let signing = provider.key_provider.load_private_key(PrivateKeyDer::Pkcs8(key))?;
    Ok(Arc::new(rustls::sign::CertifiedKey::new(vec![cert], signing)))
}

/// Picks the certificate by the ALPN a client offers: a browser (`h3` without `canopy/1`) gets the short-lived one.
#[derive(Debug)]
struct ByAlpn {
    native: Arc<rustls::sign::CertifiedKey>,
    web: Arc<WebCertificate>,
}

impl rustls::server::ResolvesServerCert for ByAlpn {
    fn resolve(&self, hello: rustls::server::ClientHello<'_>) -> Option<Arc<rustls::sign::CertifiedKey>> {
        let offered: Vec<&[u8]> = hello.alpn().map(|a| a.collect()).unwrap_or_default();
        if offered.contains(&WEB_ALPN) && !offered.contains(&canopy_protocol::ALPN) {
            Some(self.web.read().key)
        } else {
            Some(Arc::clone(&self.native))
        }
    }
}

#[cfg(unix)]
fn write_private(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let mut f = std::fs::OpenOptions::new().write(true).create(true).truncate(true).mode(0o600).open(path)?;
    f.write_all(bytes)
}

#[cfg(not(unix))]
fn write_private(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    std::fs::write(path, bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn generated_once_then_loaded_with_the_same_fingerprint() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("identity");
        let a = Identity::load_or_generate(&dir).unwrap();
        assert!(a.generated);
        let b = Identity::load_or_generate(&dir).unwrap();
        assert!(!b.generated);
        assert_eq!(a.fingerprint(), b.fingerprint());
        assert_eq!(a.fingerprint().len(), 64);
        b.server_config(&Arc::new(WebCertificate::generate(SystemTime::now()).unwrap())).unwrap();
    }

    #[test]
    fn web_certificate_is_short_lived_p256_and_rotates() {
        let t0 = SystemTime::UNIX_EPOCH + Duration::from_secs(1_800_000_000);
        let web = WebCertificate::generate(t0).unwrap();
        let first = web.fingerprint();
        // The validity as the DER carries it (UTCTime): from an hour before t0 (2027-01-15 08:00 UTC) for 10 days.
        let der = web.der();
        let has = |s: &[u8]| der.as_ref().windows(s.len()).any(|w| w == s);
        assert!(has(b"270115070000Z") && has(b"270125070000Z"), "not before / not after");
        // ECDSA with SHA-256 (1.2.840.10045.4.3.2) and the P-256 curve (1.2.840.10045.3.1.7).
        assert!(has(&[0x2a, 0x86, 0x48, 0xce, 0x3d, 0x04, 0x03, 0x02]));
        assert!(has(&[0x2a, 0x86, 0x48, 0xce, 0x3d, 0x03, 0x01, 0x07]));
        assert!(!web.rotate(t0 + WEB_CERT_ROTATION - Duration::from_secs(1)).unwrap());
        assert_eq!(web.fingerprint(), first);
        assert!(web.rotate(t0 + WEB_CERT_ROTATION).unwrap());
        assert_ne!(web.fingerprint(), first);
        let id = Identity::generate().unwrap();
        id.server_config(&Arc::new(web)).unwrap();
    }
}
