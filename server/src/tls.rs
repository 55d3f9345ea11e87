//! The server's TLS identity: a self-signed certificate generated at first start (rcgen), saved in the data
//! directory and reused, and its SHA-256 fingerprint, which clients pin.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use canopy_protocol::messages::certificate_fingerprint;
use quinn::rustls;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer};

/// Names the certificate is issued for.
pub const CERT_NAMES: [&str; 2] = ["localhost", "canopy"];

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

    /// A rustls server configuration presenting this identity with the Canopy ALPN, TLS 1.3 only.
    pub fn server_config(&self) -> Result<Arc<rustls::ServerConfig>, IdentityError> {
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let mut cfg = rustls::ServerConfig::builder_with_provider(provider)
            .with_protocol_versions(&[&rustls::version::TLS13])?
            .with_no_client_auth()
            .with_single_cert(vec![self.cert.clone()], PrivateKeyDer::Pkcs8(self.key.clone_key()))?;
        cfg.alpn_protocols = vec![canopy_protocol::ALPN.to_vec()];
        Ok(Arc::new(cfg))
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
        b.server_config().unwrap();
    }
}
