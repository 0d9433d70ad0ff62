// The content-addressed blob folder: layout, dedupe, verification on read, corruption named.
#include "db_test_util.hpp"

using namespace cf::db;
using namespace cfdbtest;

TEST(DbBlobStore, LayoutDedupeAndRead) {
    TempDir t;
    BlobStore b(t.path / "blobs");
    const auto r1 = b.put_bytes("hello");
    // sha256("hello")
    EXPECT_EQ(r1.sha256, "2cf24dba5fb0a30e26e83b2ac5b9e29e1b161e5c1fa7425e73043362938b9824");
    EXPECT_EQ(r1.size_bytes, 5);
    EXPECT_EQ(r1.path, t.path / "blobs" / "2c" / "f24dba5fb0a30e26e83b2ac5b9e29e1b161e5c1fa7425e73043362938b9824");
    EXPECT_EQ(read_file(r1.path), "hello");
    write_file(t.path / "in.bin", "hello");
    const auto r2 = b.put_file(t.path / "in.bin");
    EXPECT_EQ(r2.sha256, r1.sha256);
    EXPECT_EQ(b.read(r1.sha256), "hello");
    // One file, no temporaries left behind.
    int files = 0;
    for (const auto& e : fs::recursive_directory_iterator(t.path / "blobs"))
        if (e.is_regular_file()) ++files;
    EXPECT_EQ(files, 1);
    // Empty and larger-than-a-chunk content.
    EXPECT_EQ(b.read(b.put_bytes("").sha256), "");
    std::string big(3 * (1 << 20) + 17, '\0');
    for (std::size_t i = 0; i < big.size(); ++i) big[i] = static_cast<char>(i * 31 + 7);
    write_file(t.path / "big.bin", big);
    const auto rb = b.put_file(t.path / "big.bin");
    EXPECT_EQ(rb.size_bytes, static_cast<std::int64_t>(big.size()));
    EXPECT_EQ(rb.sha256, BlobStore::sha256_of(big));
    b.copy_to(rb.sha256, t.path / "out.bin");
    EXPECT_EQ(read_file(t.path / "out.bin"), big);
}

TEST(DbBlobStore, CorruptBlobIsNamedOnRead) {
    TempDir t;
    BlobStore b(t.path / "blobs");
    const auto r = b.put_bytes("the original content");
    write_file(r.path, "the 0riginal content");  // one byte flipped, same size
    expect_store_error([&] { b.read(r.sha256); }, StoreError::Kind::Corrupt, r.path.string());
    expect_store_error([&] { b.verify(r.sha256); }, StoreError::Kind::Corrupt, "blob is corrupt");
    expect_store_error([&] { b.copy_to(r.sha256, t.path / "copy.bin"); }, StoreError::Kind::Corrupt, r.path.string());
    EXPECT_FALSE(fs::exists(t.path / "copy.bin"));  // nothing half-written
    // Storing the same content again repairs the damaged copy.
    b.put_bytes("the original content");
    EXPECT_EQ(b.read(r.sha256), "the original content");
}

TEST(DbBlobStore, MissingAndBadNames) {
    TempDir t;
    BlobStore b(t.path / "blobs");
    const std::string absent(64, 'a');
    expect_store_error([&] { b.read(absent); }, StoreError::Kind::NotFound, "aa/aaaa");
    expect_store_error([&] { b.verify(absent); }, StoreError::Kind::NotFound, "blob missing");
    expect_store_error([&] { b.read("../../etc/passwd"); }, StoreError::Kind::Invalid, "not a SHA-256");
    expect_store_error([&] { b.read(std::string(64, 'A')); }, StoreError::Kind::Invalid, "not a SHA-256");
    expect_store_error([&] { b.put_file(t.path / "nope.bin"); }, StoreError::Kind::NotFound, "nope.bin");
    expect_store_error([&] { b.put_file(t.path); }, StoreError::Kind::Invalid, "not a regular file");
}
