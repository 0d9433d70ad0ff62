// Volume I/O through ITK, which converts NIfTI's RAS to LPS and honours direction cosines.
// Formats are chosen by extension, not through ITK's global factory registry, so the
// error for an unknown file type is ours and clear.
#include <itkGDCMImageIO.h>
#include <itkGDCMSeriesFileNames.h>
#include <itkImage.h>
#include <itkImageFileReader.h>
#include <itkImageFileWriter.h>
#include <itkImageSeriesReader.h>
#include <itkMetaImageIO.h>
#include <itkNiftiImageIO.h>
#include <itkNrrdImageIO.h>

#include <zlib.h>

#include <algorithm>
#include <cstring>
#include <filesystem>

#include "cortexfuse/core/error.hpp"
#include "itk_bridge.hpp"

namespace fs = std::filesystem;

namespace cf::itkb {
namespace {

using FloatImage = itk::Image<float, 3>;

std::string lower(std::string s) {
    std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return char(std::tolower(c)); });
    return s;
}

itk::ImageIOBase::Pointer io_for(const std::string& path) {
    const std::string name = lower(fs::path(path).filename().string());
    auto ends = [&](const std::string& e) {
        return name.size() >= e.size() && name.compare(name.size() - e.size(), e.size(), e) == 0;
    };
    if (ends(".nii") || ends(".nii.gz")) return itk::NiftiImageIO::New().GetPointer();
    if (ends(".nrrd") || ends(".nhdr")) return itk::NrrdImageIO::New().GetPointer();
    if (ends(".mha") || ends(".mhd")) return itk::MetaImageIO::New().GetPointer();
    return nullptr;
}

// ITK's description in one line, without its multi-line preamble.
std::string reason(const itk::ExceptionObject& e) {
    std::string d = e.GetDescription();
    for (auto& c : d)
        if (c == '\n' || c == '\r') c = ' ';
    if (d.size() > 300) d = d.substr(0, 300) + "...";
    return d;
}

template <class ImageT>
Grid grid_of(const ImageT* img) {
    Grid g;
    const auto size = img->GetLargestPossibleRegion().GetSize();
    for (int a = 0; a < 3; ++a) {
        g.dims[a] = int(std::min<size_t>(size[a], size_t(1) << 30));
        g.spacing[a] = img->GetSpacing()[a];
        g.origin[a] = img->GetOrigin()[a];
        for (int b = 0; b < 3; ++b) g.direction[a * 3 + b] = img->GetDirection()(a, b);
    }
    return g;
}

template <class ImageT>
typename ImageT::Pointer make_image(const Grid& g) {
    auto img = ImageT::New();
    typename ImageT::RegionType region;
    typename ImageT::SizeType size;
    typename ImageT::SpacingType spacing;
    typename ImageT::PointType origin;
    typename ImageT::DirectionType dir;
    for (int a = 0; a < 3; ++a) {
        size[a] = g.dims[a];
        spacing[a] = g.spacing[a];
        origin[a] = g.origin[a];
        for (int b = 0; b < 3; ++b) dir(a, b) = g.direction[a * 3 + b];
    }
    region.SetSize(size);
    img->SetRegions(region);
    img->SetSpacing(spacing);
    img->SetOrigin(origin);
    img->SetDirection(dir);
    img->Allocate();
    return img;
}

// ITK's NIfTI reader accepts a truncated .nii.gz and returns zeros for the missing part,
// so the byte count the header promises is checked here first (the whole gzip stream is
// read and its CRC checked by zlib).
void check_nifti_complete(const std::string& path) {
    gzFile f = gzopen(path.c_str(), "rb");
    if (!f) throw InputError(path, "cannot open file");
    unsigned char hdr[348];
    const int got = gzread(f, hdr, sizeof hdr);
    if (got < int(sizeof hdr)) {
        gzclose(f);
        throw InputError(path, "truncated NIfTI header");
    }
    int32_t sizeof_hdr;
    std::memcpy(&sizeof_hdr, hdr, 4);
    if (sizeof_hdr != 348) {  // NIfTI-2 or byte-swapped: leave the check to ITK
        gzclose(f);
        return;
    }
    int16_t dim[8], bitpix;
    float vox_offset;
    std::memcpy(dim, hdr + 40, sizeof dim);
    std::memcpy(&bitpix, hdr + 72, 2);
    std::memcpy(&vox_offset, hdr + 108, 4);
    uint64_t voxels = 1;
    for (int d = 1; d <= std::clamp<int>(dim[0], 1, 7); ++d) voxels *= uint64_t(std::max<int16_t>(dim[d], 1));
    const uint64_t expected = uint64_t(std::max(vox_offset, 348.f)) + voxels * uint64_t(std::max<int16_t>(bitpix, 8) / 8);
    uint64_t total = sizeof hdr;
    std::vector<unsigned char> buf(1 << 20);
    int n;
    while ((n = gzread(f, buf.data(), unsigned(buf.size()))) > 0) total += uint64_t(n);
    int err = Z_OK;
    const char* msg = gzerror(f, &err);
    const std::string zmsg = msg ? msg : "";
    gzclose(f);
    if (n < 0 || (err != Z_OK && err != Z_STREAM_END))
        throw InputError(path, "truncated or corrupt compressed data (" + zmsg + ")");
    if (total < expected)
        throw InputError(path, "truncated volume: " + std::to_string(total) + " bytes of " + std::to_string(expected) +
                                   " the header promises");
}

FloatImage::Pointer read_series(const std::string& dir, void (*check)(const Grid&, const std::string&)) {
    auto names = itk::GDCMSeriesFileNames::New();
    names->SetUseSeriesDetails(true);
    std::vector<std::string> series;
    try {
        names->SetDirectory(dir);
        series = names->GetSeriesUIDs();
    } catch (const itk::ExceptionObject& e) {
        throw InputError(dir, "cannot scan for DICOM: " + reason(e));
    }
    if (series.empty()) throw InputError(dir, "folder holds no DICOM series");
    if (series.size() > 1)
        throw InputError(dir, "folder holds " + std::to_string(series.size()) + " DICOM series; put one series per folder");
    const auto files = names->GetFileNames(series.front());
    if (files.size() < 2) throw InputError(dir, "DICOM series has fewer than 2 slices");
    auto reader = itk::ImageSeriesReader<FloatImage>::New();
    reader->SetImageIO(itk::GDCMImageIO::New());
    reader->SetFileNames(files);
    try {
        reader->UpdateOutputInformation();
        check(grid_of(reader->GetOutput()), dir);
        reader->Update();
    } catch (const itk::ExceptionObject& e) {
        throw InputError(dir, "unreadable DICOM series: " + reason(e));
    }
    return reader->GetOutput();
}

}  // namespace

void read_float(const std::string& path, Grid& grid, std::vector<float>& voxels,
                void (*check)(const Grid&, const std::string&)) {
    std::error_code ec;
    if (!fs::exists(path, ec)) throw InputError(path, "no such file or folder");
    itk::Object::GlobalWarningDisplayOff();  // our errors say it in one line instead
    FloatImage::Pointer img;
    if (fs::is_directory(path, ec)) {
        img = read_series(path, check);
    } else {
        auto io = io_for(path);
        if (!io)
            throw InputError(path, "unknown volume format (expected .nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd or a DICOM folder)");
        if (!io->CanReadFile(path.c_str())) throw InputError(path, std::string("not a readable ") + io->GetNameOfClass() + " file");
        if (std::string(io->GetNameOfClass()) == "NiftiImageIO") check_nifti_complete(path);
        auto reader = itk::ImageFileReader<FloatImage>::New();
        reader->SetImageIO(io);
        reader->SetFileName(path);
        try {
            reader->UpdateOutputInformation();
            // Refuse absurd headers before ITK allocates for them.
            check(grid_of(reader->GetOutput()), path);
            reader->Update();
        } catch (const itk::ExceptionObject& e) {
            throw InputError(path, "unreadable or truncated volume: " + reason(e));
        }
        img = reader->GetOutput();
    }
    grid = grid_of(img.GetPointer());
    const float* p = img->GetBufferPointer();
    voxels.assign(p, p + grid.count());
}

namespace {
template <class PixelT>
void write_image(const std::string& path, const Grid& g, const PixelT* data) {
    using ImageT = itk::Image<PixelT, 3>;
    auto io = io_for(path);
    if (!io) throw InputError(path, "unknown volume format to write (use .nii.gz, .nrrd or .mha)");
    auto img = make_image<ImageT>(g);
    std::copy(data, data + g.count(), img->GetBufferPointer());
    auto w = itk::ImageFileWriter<ImageT>::New();
    w->SetImageIO(io);
    w->SetFileName(path);
    w->SetInput(img);
    w->SetUseCompression(true);
    try {
        w->Update();
    } catch (const itk::ExceptionObject& e) {
        throw InputError(path, "cannot write volume: " + reason(e));
    }
}
}  // namespace

void write_float(const std::string& path, const Grid& grid, const float* voxels) { write_image(path, grid, voxels); }
void write_u8(const std::string& path, const Grid& grid, const uint8_t* voxels) { write_image(path, grid, voxels); }

}  // namespace cf::itkb
