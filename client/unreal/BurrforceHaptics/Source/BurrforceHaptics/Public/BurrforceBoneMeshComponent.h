// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// The carved bone, drawn: a procedural mesh with one section per mesh chunk (proto/MESH.md),
// kept current by the core's MeshSync on a worker thread (REST, polled when the REPLYs'
// bone_version moves). Frame `unreal` (cm, world coordinates), winding `cw` as Unreal draws
// front faces. The component is held at the world origin: the vertices are world positions.

#pragma once

#include "CoreMinimal.h"
#include "ProceduralMeshComponent.h"
#include "BurrforceBoneMeshComponent.generated.h"

class UBurrforceComponent;
class UMaterialInterface;
struct FBurrforceMeshRuntime;

UCLASS(ClassGroup = (Haptics), meta = (BlueprintSpawnableComponent))
class BURRFORCEHAPTICS_API UBurrforceBoneMeshComponent : public UProceduralMeshComponent
{
	GENERATED_BODY()

public:
	UBurrforceBoneMeshComponent(const FObjectInitializer& ObjectInitializer);

	/// The streaming component whose session to draw. None: the owner's first one.
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Mesh")
	TObjectPtr<UBurrforceComponent> Source;

	/// Chunk edge in 8-voxel bricks (1-8); 0: the server's default. Smaller chunks re-upload
	/// less per cut, larger ones mean fewer sections.
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Mesh",
		meta = (ClampMin = "0", ClampMax = "8"))
	int32 ChunkBricks = 0;

	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Mesh")
	TObjectPtr<UMaterialInterface> BoneMaterial;

	/// Sections re-uploaded per frame at most (the rest follow next frame): bounds the
	/// render-thread cost of a big update such as the first full copy.
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Mesh",
		meta = (ClampMin = "1"))
	int32 MaxSectionsPerTick = 64;

	/// Vertex colour per material label (index = label); labels beyond it are white.
	UPROPERTY(EditAnywhere, BlueprintReadWrite, Category = "Burrforce|Mesh")
	TArray<FColor> LabelColors;

	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Mesh")
	int32 ChunkCount = 0;

	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Mesh")
	int64 MeshBoneVersion = 0;

	UPROPERTY(BlueprintReadOnly, Category = "Burrforce|Mesh")
	int64 SyncErrors = 0;

	virtual void TickComponent(float DeltaTime, ELevelTick TickType,
		FActorComponentTickFunction* ThisTickFunction) override;

protected:
	virtual void BeginPlay() override;
	virtual void EndPlay(const EEndPlayReason::Type EndPlayReason) override;

private:
	void TryStart();
	void UploadPending();

	TSharedPtr<FBurrforceMeshRuntime> Runtime;
	TMap<FIntVector, int32> SectionOfChunk;
	TArray<int32> FreeSections;
};
